"""Whole leaderboards in memory, for the API and the leaderboard pages: a phase's board read
once, then kept current by the entries that come and go, shared by every page, page size,
sort and format.

A request takes its phase's snapshot as it is for `max_age` seconds after the snapshot's version
was last confirmed; then the version is read again (one indexed lookup). When it has moved, one
thread brings the snapshot up to date while the others go on serving the one they have, so no
request waits for another's read (but the very first of a phase's).

Bringing a snapshot up to date reads the ids of the phase's rows (an index-only scan) and only
the rows it does not hold yet: the entries that went are dropped, those that came are put in
their place, ranks are counted again from the first place that changed, and the tie groups are
counted again whole from the paired tests kept, testing only the neighbours that are new
(`server.leaderboard.ties`: Holm's correction depends on every comparison). A change
costs milliseconds where reading the whole board again costs a fifth of a second, during which
the thread holds the interpreter. A full read happens for a phase's first snapshot, when its
columns changed, when most of the board did (a rebuild), and on SQLite (`STABLE_IDS`). What is
derived from one entry alone (`server.leaderboard.stored`) is made once and kept across
snapshots.
"""

from __future__ import annotations

import bisect
import gc
import json
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

from sqlalchemy import Text, cast, func, select
from sqlalchemy.orm import Session as DB

from evaluator.results import Environment
from server.challenges.service import get_challenge
from server.leaderboard.schemas import LeaderboardOut
from server.leaderboard.service import (
    Interval,
    Row,
    board_query,
    interval_of_summary,
    phase_versions,
    suite_columns,
    suite_environment,
)
from server.leaderboard.stored import Place, Stored, csv_header
from server.leaderboard.ties import TieGroups, count_groups, outcomes_of
from server.models import Challenge, LeaderboardEntry, Phase

INCREMENT_SHARE = 0.5
INCREMENT_MIN = 64
"""Past this share of the board (and this many rows) come or gone, a snapshot is read whole
again."""
EXEMPT_MIN_ROWS = 100
"""A phase's first board is exempted from the cyclic garbage collector (`_exempt_from_gc`) when
it has at least this many rows: exempting costs a full collection, which a board of a few rows
never pays back."""
STABLE_IDS = frozenset({"postgresql"})
"""Databases that never give a deleted row's id to a new one (a sequence), so that an id always
means one row. SQLite reuses the highest ids once their rows are gone: there, a snapshot is
read whole on every change (SQLite serves one process and small boards)."""


BoardKey = tuple[str, str, int | None]
"""A challenge's slug, a phase's name, and a board version (None: the current one)."""
Sort = tuple[str, bool, int]  # a sort key's name, descending, how many rows it sorts


@dataclass
class Snapshot:
    """A phase's whole board at one version, rows in rank order."""

    slug: str
    phase: str
    phase_id: int  # a phase removed and made again under its name starts at version 0 again
    version: int  # the phase's leaderboard version (the cache key) it was read at
    board_version: int  # which evaluation of the phase it shows (docs/server.md, Re-evaluation)
    rows: list[Stored]
    ranks: list[int | None]  # None for unranked rows: baselines, disqualified ones
    ties: TieGroups
    alpha: float  # the phase's significance level, at which the tie groups are drawn
    tasks: list[str]
    conditions: list[str]
    suite_hash: str  # names the columns (tasks and conditions)
    environment: Environment | None = None  # the suite's now, which rows are compared with
    hidden: bool = False
    """A hidden board not published yet: each viewer sees their own rows (`shown_to`)."""
    checked: float = field(default_factory=time.monotonic)
    by_id: dict[int, Stored] = field(init=False)
    sorted_rows: dict[Sort, tuple[frozenset[int], list[Stored]]] = field(default_factory=dict)
    """Sorted views of the first rows (by their serials), the last snapshot's until remade."""
    _sorted: dict[Sort, list[int]] = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.by_id = {stored.id: stored for stored in self.rows}

    @property
    def total(self) -> int:
        return len(self.rows)

    @property
    def groups(self) -> list[int | None]:
        return self.ties.groups

    @property
    def tied(self) -> list[bool]:
        return self.ties.tied

    def place(self, index: int) -> Place:
        """The rank, tie and tie group of the row at this place."""
        return self.ranks[index], self.ties.tied[index], self.ties.groups[index]

    def ready(self, page: int, per_page: int, format: str) -> bool:
        """Whether every row of the page is serialized already (a page then costs a join)."""
        shown = self.rows[(page - 1) * per_page : page * per_page]
        return all(s.serialized(format) for s in shown)

    def body(self, page: int, per_page: int, format: str) -> bytes:
        """The page as the API sends it, JSON or CSV."""
        start, stop = (page - 1) * per_page, min(page * per_page, len(self.rows))
        cols = self.tasks, self.conditions
        if format == "csv":
            lines = [csv_header(*cols)]
            lines += [self.rows[i].csv(cols, self.place(i)) for i in range(start, stop)]
            return "".join(lines).encode()
        items = b",".join(self.rows[i].json(cols, self.place(i)) for i in range(start, stop))
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

    def row(self, index: int) -> Row:
        """The row at this place in rank order, as the pages show it."""
        shown = self.rows[index].row(self.tasks, self.conditions)
        rank, tied, group = self.place(index)
        return replace(shown, rank=rank, tied=tied, tie_group=group)

    def shown_to(self, *, organizer: bool, own: Callable[[Stored], bool]) -> Snapshot:
        """The board as a viewer may see it: whole, unless it is hidden and they are not an
        organizer; then their own rows alone, without rank or tie group, which would tell
        them of the others'."""
        if not self.hidden or organizer:
            return self
        rows = [s for s in self.rows if own(s)]
        blank: list[int | None] = [None] * len(rows)
        return replace(
            self,
            rows=rows,
            ranks=blank,
            ties=TieGroups(groups=list(blank), tied=[False] * len(rows), p_values={}),
            sorted_rows={},
        )

    def order(
        self, key: Callable[[Row], Any], name: str, descending: bool, limit: int
    ) -> list[int]:
        """The places of the first `limit` rows in rank order, sorted by `key` (rows without a
        value last either way); kept per snapshot under `name`, and carried over to the next
        snapshot while those rows are the same ones (whatever their ranks)."""
        sort = (name, descending, limit)
        if (found := self._sorted.get(sort)) is not None:
            return found
        window = self.rows[:limit]
        members = frozenset(s.serial for s in window)
        known = self.sorted_rows.get(sort)
        if known is not None and known[0] == members:
            ordered = known[1]
        else:
            cols = self.tasks, self.conditions
            values = [(s, s.sort_value(name, key, cols)) for s in window]
            present = [(s, v) for s, v in values if v is not None]
            present.sort(key=lambda sv: sv[1], reverse=descending)
            ordered = [s for s, _ in present] + [s for s, v in values if v is None]
        self.sorted_rows[sort] = (members, ordered)
        place = {s.serial: i for i, s in enumerate(window)}
        found = self._sorted[sort] = [place[s.serial] for s in ordered]
        return found


class Snapshots:
    """The current snapshot of every phase asked for, and of each earlier board version asked
    for by number (a few per challenge: bounded by the phases and versions that exist, as an
    unknown one raises before anything is kept)."""

    def __init__(self, max_age: float) -> None:
        self._max_age = max_age
        self._boards: dict[BoardKey, Snapshot] = {}
        self._reading: set[BoardKey] = set()
        self._lock = threading.Lock()
        self._read = threading.Condition(self._lock)  # notified when a look is over

    def fresh(self, slug: str, phase: str, board_version: int | None = None) -> Snapshot | None:
        """The phase's snapshot (of `board_version`; None: the current one) while it is trusted
        without a look at the database: for `max_age` seconds after its version was confirmed,
        and while another thread is confirming it or bringing it up to date."""
        key = (slug, phase, board_version)
        with self._lock:
            found = self._boards.get(key)
            checking = key in self._reading
        if found is None or (time.monotonic() - found.checked >= self._max_age and not checking):
            return None
        return found

    def current(
        self,
        sessions: Callable[[], DB],
        *,
        slug: str,
        phase: str,
        board_version: int | None = None,
    ) -> Snapshot:
        """The phase's snapshot (of `board_version`; None: the current one), its version
        confirmed or brought up to date (blocking)."""
        with sessions() as db:
            return self.current_in(db, slug=slug, phase=phase, board_version=board_version)

    def current_in(
        self, db: DB, *, slug: str, phase: str, board_version: int | None = None
    ) -> Snapshot:
        """`current`, in a session the caller holds."""
        key = (slug, phase, board_version)
        with self._lock:
            waited = False
            while (held := self._boards.get(key)) is None and key in self._reading:
                self._read.wait()  # a phase's first read: one thread reads, the others wait
                waited = True
            if held is not None and (waited or key in self._reading):
                return held  # another thread looks at the database: this one may lag
            self._reading.add(key)
        try:
            phase_id, version, shown = phase_versions(  # 404/422 first
                db, slug=slug, phase=phase, version=board_version
            )
            if held is not None and (held.phase_id, held.version) == (phase_id, version):
                held.checked = time.monotonic()
                return held
            same = held if held is not None and held.phase_id == phase_id else None
            if same is not None and same.board_version != shown:
                same = None  # a re-evaluation was published: another board
            read = advance(db, same, version=version) if same is not None else None
            if read is None:
                read = read_whole(
                    db,
                    slug=slug,
                    phase=phase,
                    phase_id=phase_id,
                    version=version,
                    board_version=shown,
                    held=same,
                )
                if held is None and len(read.rows) >= EXEMPT_MIN_ROWS:
                    _exempt_from_gc()  # the phase's first board in this process
            with self._lock:
                kept = self._boards.get(key)
                if kept is None or kept.phase_id != read.phase_id or kept.version <= read.version:
                    self._boards[key] = read
            return read
        finally:
            with self._lock:
                self._reading.discard(key)
                self._read.notify_all()


def _exempt_from_gc() -> None:
    """After a whole read: exempt what lives now, the new board included, from the cyclic
    garbage collector. A board is tens of thousands of long-lived objects that every full
    collection walked, pausing each request in flight for 100 ms and more under load
    (bench/leaderboard_load.py: p95 45-54 ms before, 28-38 ms after). Done once per phase and
    process, at its first board if it has `EXEMPT_MIN_ROWS` rows: what else lives at that
    moment and later becomes garbage with cycles is never collected, so it is not done again.
    Garbage with cycles is collected first; rows hold no cycles, so a board dropped later is
    freed by reference counts."""
    gc.collect()
    gc.freeze()


def _summary_columns() -> tuple[Any, ...]:
    # The summary as text, and only its score interval as JSON: every row's interval is shown,
    # the rest is parsed when a page shows the row. The outcomes, which the tie groups need of
    # every row, are parsed once per row.
    summary = LeaderboardEntry.summary
    interval_at = [summary[("score_interval", end)].as_float() for end in (0, 1)]
    text = cast(summary, Text).label("summary_text")
    ends = interval_at[0].label("ci_low"), interval_at[1].label("ci_high")
    # Whether (and why) it is disqualified decides its place: read with the row, not parsed.
    disqualified = summary["disqualified"].as_string().label("disqualified")
    return text, *ends, disqualified, LeaderboardEntry.outcomes


def _interval(db: DB, entry: Any) -> Interval:
    if entry.ci_low is not None and entry.ci_high is not None:
        return (entry.ci_low, entry.ci_high)
    return interval_of_summary(db, json.loads(entry.summary_text), entry.submission_id)


def read_whole(
    db: DB,
    *,
    slug: str,
    phase: str,
    phase_id: int,
    version: int,
    board_version: int,
    held: Snapshot | None = None,
) -> Snapshot:
    """Version `board_version` of the phase's board read whole (what `held`, of this phase
    and board version, derived already is kept)."""
    entries = db.execute(board_query(phase_id, board_version, *_summary_columns())).all()
    challenge = get_challenge(db, slug=slug)
    tasks, conditions = suite_columns(challenge)
    current = suite_environment(challenge)
    keep: dict[int, Stored] = {}
    shown = (tasks, conditions, current)  # a row's mark is against the current environment
    if held is not None and (held.tasks, held.conditions, held.environment) == shown:
        keep = held.by_id if db.get_bind().dialect.name in STABLE_IDS else {}
    read = [keep.get(entry.id) or _stored(db, entry, current) for entry in entries]
    # The database's rank order, with disqualified rows moved after the others (`Stored.key`).
    rows = [s for s in read if s.disqualified is None] + [
        s for s in read if s.disqualified is not None
    ]
    ranks: list[int | None] = []
    _rank((s.unranked for s in rows), ranks)
    found = next(p for p in challenge.phases if p.id == phase_id)
    alpha = found.significance_level
    known = held.ties.p_values if held is not None else {}
    ties = count_groups(db, rows, ranks, alpha=alpha, known=known)
    return Snapshot(
        slug,
        phase,
        phase_id,
        version,
        board_version,
        rows,
        ranks,
        ties,
        alpha,
        tasks,
        conditions,
        challenge.suite_hash,
        environment=current,
        hidden=not found.board_shown_to_all(),
    )


def _stored(db: DB, entry: Any, current: Environment | None) -> Stored:
    interval, outcomes = _interval(db, entry), outcomes_of(db, entry)
    return Stored(entry, entry.summary_text, interval, outcomes, current)


def advance(db: DB, held: Snapshot, *, version: int) -> Snapshot | None:
    """`held` brought up to `version` by the entries that came and went since it was read;
    None when a whole read is due (columns changed, most of the board did, or a row read as
    present went before it could be read), and always on a database that reuses ids."""
    if db.get_bind().dialect.name not in STABLE_IDS:
        return None
    found = db.execute(
        select(Challenge.suite_hash, Phase.significance_level, Phase)
        .join(Phase, Phase.challenge_id == Challenge.id)
        .where(Phase.id == held.phase_id)
    ).first()
    if found is None or found[0] != held.suite_hash:
        return None  # its columns may have changed
    e = LeaderboardEntry
    ids = select(func.array_agg(e.id)).where(
        e.phase_id == held.phase_id, e.board_version == held.board_version
    )
    now = set(db.connection().execute(ids).scalar() or ())  # one array: no row per id
    gone = held.by_id.keys() - now
    came = now - held.by_id.keys()
    if len(gone) + len(came) > max(INCREMENT_MIN, len(held.rows) * INCREMENT_SHARE):
        return None
    new: list[Stored] = []
    if came:
        query = board_query(held.phase_id, held.board_version, *_summary_columns())
        query = query.where(e.id.in_(came))
        current = held.environment
        new = [_stored(db, r, current) for r in db.execute(query)]
        if len(new) != len(came):
            return None  # refreshed between the two reads: the ids are not one state
    rows = [s for s in held.rows if s.id not in gone] if gone else list(held.rows)
    for stored in new:
        bisect.insort(rows, stored, key=lambda s: s.key)
    first = next(
        (i for i, (a, b) in enumerate(zip(rows, held.rows, strict=False)) if a is not b),
        min(len(rows), len(held.rows)),
    )
    ranks = held.ranks[:first]
    _rank_from(rows, first, ranks)
    alpha = found[1]
    return Snapshot(
        held.slug,
        held.phase,
        held.phase_id,
        version,
        held.board_version,
        rows,
        ranks,
        count_groups(db, rows, ranks, alpha=alpha, known=held.ties.p_values),
        alpha,
        held.tasks,
        held.conditions,
        held.suite_hash,
        environment=held.environment,
        hidden=not found[2].board_shown_to_all(),
        sorted_rows=dict(held.sorted_rows),
    )


def _rank_from(rows: list[Stored], first: int, ranks: list[int | None]) -> None:
    """Extend `ranks`, right up to `first`, to every row."""
    rank = next((found for found in reversed(ranks[:first]) if found is not None), 0)
    _rank((s.unranked for s in rows[first:]), ranks, rank=rank)


def _rank(unranked: Iterable[bool], ranks: list[int | None], *, rank: int = 0) -> None:
    """Append the rank of each row in rank order (given whether it is unranked: a baseline or
    disqualified), after a ranked row of `rank`."""
    for alone in unranked:
        if alone:
            ranks.append(None)
            continue
        rank += 1
        ranks.append(rank)
