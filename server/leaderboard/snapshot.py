"""Whole leaderboards in memory, for the API: one read of a phase's board per version, shared by
every page, page size and format.

A request takes its phase's snapshot as it is for `max_age` seconds after the snapshot's version
was last confirmed; then the version is read again (one indexed lookup). When it has moved, one
thread reads the board again while the others go on serving the snapshot they have, so a board
that changes every second costs one read per `max_age`, however many distinct pages are asked
for, and no request waits for another's read (but the very first of a phase's). Rows are
serialized once per snapshot, when a page first shows them.
"""

from __future__ import annotations

import csv
import io
import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import Text, cast
from sqlalchemy.orm import Session as DB

from server.leaderboard.schemas import LeaderboardOut, LeaderboardRowOut
from server.leaderboard.service import (
    Interval,
    Row,
    board_query,
    board_row,
    board_version,
    column_order,
    interval_of_summary,
    ranked,
    read_meta,
)
from server.models import LeaderboardEntry

CSV_HEADER = ["rank", "username", "baseline", "score", "score_ci_low", "score_ci_high", "tied"]
CSV_HEADER += ["submitted_at", "submission_id", "team", "team_display_name", "method"]
CSV_HEADER += ["paper_url", "code_url"]


@dataclass(frozen=True)
class Ranked:
    """A row of a snapshot before it is shown: its summary still JSON text, parsed only when a
    page first shows the row (most rows of a board that changes every second never are)."""

    entry: Any
    summary_text: str
    rank: int | None
    interval: Interval
    tied: bool


@dataclass
class Snapshot:
    """A phase's whole board at one version, rows in rank order."""

    slug: str
    phase: str
    phase_id: int  # a phase removed and made again under its name starts at version 0 again
    version: int
    rows: list[Ranked]
    tasks: list[str]
    conditions: list[str]
    checked: float = field(default_factory=time.monotonic)
    _json: list[bytes | None] = field(default_factory=list)
    _csv: list[str | None] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._json = [None] * len(self.rows)
        self._csv = [None] * len(self.rows)

    def ready(self, page: int, per_page: int, format: str) -> bool:
        """Whether every row of the page is serialized already (a page then costs a join)."""
        done = self._json if format == "json" else self._csv
        return all(item is not None for item in done[(page - 1) * per_page : page * per_page])

    def body(self, page: int, per_page: int, format: str) -> bytes:
        """The page as the API sends it, JSON or CSV."""
        start, stop = (page - 1) * per_page, min(page * per_page, len(self.rows))
        if format == "csv":
            return self._csv_page(start, stop).encode()
        items = b",".join(self._json_row(i) for i in range(start, stop))
        envelope = LeaderboardOut(
            challenge=self.slug,
            phase=self.phase,
            page=page,
            per_page=per_page,
            total=len(self.rows),
            tasks=self.tasks,
            conditions=self.conditions,
            items=[],
        ).model_dump_json()
        head, found, tail = envelope.partition('"items":[]')
        assert found, "LeaderboardOut serializes its items as a list"
        return head.encode() + b'"items":[' + items + b"]" + tail.encode()

    def _json_row(self, index: int) -> bytes:
        if (done := self._json[index]) is None:
            done = self._json[index] = self._out(index).model_dump_json().encode()
        return done

    def _out(self, index: int) -> LeaderboardRowOut:
        r = self.rows[index]
        row: Row = board_row(r.entry, json.loads(r.summary_text), r.rank, r.interval, r.tied)
        shown = row.in_order(tasks=self.tasks, conditions=self.conditions)
        return LeaderboardRowOut(**shown.__dict__)

    def _csv_page(self, start: int, stop: int) -> str:
        buf = io.StringIO()
        header = CSV_HEADER + [f"{t} success" for t in self.tasks]
        header += [f"{t} ci_low" for t in self.tasks] + [f"{t} ci_high" for t in self.tasks]
        header += [f"condition {c}" for c in self.conditions]
        csv.writer(buf).writerow(header)
        for index in range(start, stop):
            if (line := self._csv[index]) is None:
                line = self._csv[index] = self._csv_line(index)
            buf.write(line)
        return buf.getvalue()

    def _csv_line(self, index: int) -> str:
        row, buf = self._out(index), io.StringIO()
        cells: list[object] = [
            row.rank if row.rank is not None else "",
            csv_safe(row.username),
            row.baseline,
            f"{row.score:.4f}",
            f"{row.score_ci_low:.4f}" if row.score_ci_low is not None else "",
            f"{row.score_ci_high:.4f}" if row.score_ci_high is not None else "",
            row.tied,
            row.submitted_at.isoformat(),
            row.submission_id,
            row.team or "",
            csv_safe(row.team_display_name or ""),
            csv_safe(row.method or ""),
            row.paper_url or "",
            row.code_url or "",
        ]
        for key in ("success_rate", "ci_low", "ci_high"):
            cells += [f"{row.tasks[t][key]:.4f}" if t in row.tasks else "" for t in self.tasks]
        cells += [
            f"{row.conditions[c]:.4f}" if c in row.conditions else "" for c in self.conditions
        ]
        csv.writer(buf).writerow(cells)
        return buf.getvalue()


def csv_safe(text: str) -> str:
    """Spreadsheets run cells starting with = + - @ as formulas: defuse them."""
    return "'" + text if text[:1] in ("=", "+", "-", "@") else text


class Snapshots:
    """The current snapshot of every phase asked for (a few per challenge: bounded by the
    phases that exist, as an unknown one raises before anything is kept)."""

    def __init__(self, max_age: float) -> None:
        self._max_age = max_age
        self._boards: dict[tuple[str, str], Snapshot] = {}
        self._reading: set[tuple[str, str]] = set()
        self._lock = threading.Lock()

    def fresh(self, slug: str, phase: str) -> Snapshot | None:
        """The phase's snapshot while it is trusted without a look at the database."""
        with self._lock:
            found = self._boards.get((slug, phase))
        if found is None or time.monotonic() - found.checked >= self._max_age:
            return None
        return found

    def current(self, sessions: Callable[[], DB], *, slug: str, phase: str) -> Snapshot:
        """The phase's snapshot, its version confirmed or read again (blocking: a thread's)."""
        key = (slug, phase)
        with self._lock:
            held = self._boards.get(key)
        with sessions() as db:
            phase_id, version = board_version(db, slug=slug, phase=phase)  # 404/422 first
            if held is not None and (held.phase_id, held.version) == (phase_id, version):
                held.checked = time.monotonic()
                return held
            with self._lock:
                if held is not None and key in self._reading:
                    return held  # another thread reads the new version: this one may lag
                self._reading.add(key)
            try:
                read = _read(db, slug=slug, phase=phase, phase_id=phase_id, version=version)
            finally:
                with self._lock:
                    self._reading.discard(key)
        with self._lock:
            kept = self._boards.get(key)
            if kept is None or kept.phase_id != read.phase_id or kept.version <= read.version:
                self._boards[key] = read
        return read


def _read(db: DB, *, slug: str, phase: str, phase_id: int, version: int) -> Snapshot:
    # The summary as text, and only its score interval as JSON: ranks and ties need every
    # row's interval, the rest is parsed when a page shows the row.
    summary = LeaderboardEntry.summary
    text_of = cast(summary, Text).label("summary_text")
    interval_at = [summary[("score_interval", end)].as_float() for end in (0, 1)]
    columns = (text_of, interval_at[0].label("ci_low"), interval_at[1].label("ci_high"))
    entries = db.execute(board_query(phase_id, *columns)).all()

    def interval(entry: Any) -> Interval:
        if entry.ci_low is not None and entry.ci_high is not None:
            return (entry.ci_low, entry.ci_high)
        return interval_of_summary(db, json.loads(entry.summary_text), entry.submission_id)

    rows = [
        Ranked(entry, entry.summary_text, rank, found, tied)
        for entry, rank, found, tied in ranked(
            db, phase_id, 0, entries, read_meta(db, phase_id), interval
        )
    ]
    tasks, conditions = column_order(db, slug=slug)
    return Snapshot(slug, phase, phase_id, version, rows, tasks, conditions)
