"""One stored leaderboard row and what is derived from it alone, made once and kept across a
phase's snapshots: its row as the pages show it, its JSON and its CSV line, less its rank and
tie group, which are the snapshot's.

An entry's id always means the same content: `server.standings.entries` never updates a row
in place (a refresh deletes the rows it recomputes and inserts new ones), so what is derived
from an entry stays true for as long as the entry is on the board.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
from collections.abc import Callable, Hashable, Sequence
from typing import Any

from evaluator.paired import PackedOutcomes
from evaluator.results import Environment
from server.kit.spreadsheets import csv_safe
from server.leaderboard.schemas import LeaderboardRowOut
from server.leaderboard.service import Interval, Row, board_row

CSV_HEADER = ["rank", "username", "baseline", "score", "score_ci_low", "score_ci_high", "tied"]
CSV_HEADER += ["tie_group", "submitted_at", "submission_id", "team", "team_display_name", "method"]
CSV_HEADER += ["paper_url", "code_url", "disqualified"]
ENVIRONMENT_COLUMN = "environment_differs"
"""The CSV's last column: the environment fields that differ, joined by ";"."""


_SERIALS = itertools.count(1)

Place = tuple[int | None, bool, int | None]
"""Where a snapshot puts a row: its rank, whether it is tied with the ranked row above (in its
tie group), and its tie group (None, None for an unranked row: a baseline, a disqualified one)."""


def _json_int(n: int | None) -> bytes:
    return b"null" if n is None else str(n).encode()


def csv_header(tasks: Sequence[str], conditions: Sequence[str]) -> str:
    """The CSV's first line for a board with these columns."""
    header = CSV_HEADER + [f"{t} success" for t in tasks]
    header += [f"{t} ci_low" for t in tasks] + [f"{t} ci_high" for t in tasks]
    header += [f"condition {c}" for c in conditions]
    return _csv_line([*header, ENVIRONMENT_COLUMN])


def _csv_line(cells: Sequence[object]) -> str:
    buf = io.StringIO()
    csv.writer(buf).writerow(cells)
    return buf.getvalue()


ENTRY_FIELDS = (
    "id",
    "username",
    "submission_id",
    "baseline",
    "score",
    "submitted_at",
    "team_name",
    "team_display_name",
    "method",
    "paper_url",
    "code_url",
)
"""What a row keeps of its entry's columns (`server.leaderboard.service.BOARD_COLUMNS`)."""


class Stored:
    """A board row as stored, its summary still JSON text: parsed only when a page shows the
    row. The derived forms follow the column order of the snapshots that share this object,
    which is one order.

    Few objects the garbage collector tracks: the entry's columns are kept as plain values (not
    the database row), and the parsed row is not kept (only what is made of it: text, bytes,
    and sort values), since every full collection walks every tracked object of the process.
    """

    __slots__ = (
        *ENTRY_FIELDS,
        "_csv",
        "_html",
        "_json",
        "_sorts",
        "current",
        "disqualified",
        "interval",
        "key",
        "outcomes",
        "serial",
        "summary",
    )

    id: int
    username: str
    submission_id: int
    baseline: bool
    score: float
    submitted_at: Any
    team_name: str | None
    team_display_name: str | None
    method: str | None
    paper_url: str | None
    code_url: str | None

    def __init__(
        self,
        entry: Any,
        summary_text: str,
        interval: Interval,
        outcomes: PackedOutcomes | None = None,
        current: Environment | None = None,
    ) -> None:
        for name in ENTRY_FIELDS:
            setattr(self, name, getattr(entry, name))
        self.serial = next(_SERIALS)
        """Unique in the process, never reused: names this object's content (an entry id may
        be given to another row on SQLite)."""
        self.summary = summary_text
        self.interval = interval
        self.outcomes = outcomes
        """The ranked condition's episodes, packed: what the tie groups pair."""
        self.current = current
        """The environment the row's is compared with: the suite's now (`Snapshot`)."""
        self.disqualified: str | None = getattr(entry, "disqualified", None)
        """Why the organizers disqualified it (its summary's), or None."""
        self.key: tuple[bool, float, Any, int] = (
            self.disqualified is not None,
            -entry.score,
            entry.submitted_at,
            entry.id,
        )
        """The rank order: disqualified rows after the others, then higher score, then
        earlier, then lower id (the database's order)."""
        self._json: bytes | None = None
        self._csv: tuple[str, str] | None = None
        self._html: tuple[Hashable, str] | None = None
        self._sorts: dict[str, Any] | None = None

    @property
    def unranked(self) -> bool:
        """A baseline or a disqualified row: on the board without a rank."""
        return self.baseline or self.disqualified is not None

    def row(self, tasks: Sequence[str], conditions: Sequence[str]) -> Row:
        """The row as pages show it, unranked and in no tie group."""
        done = board_row(self, json.loads(self.summary), None, self.interval, self.current)
        return done.in_order(tasks=tasks, conditions=conditions)

    def sort_value(
        self, name: str, key: Callable[[Row], Any], cols: tuple[Sequence[str], Sequence[str]]
    ) -> Any:
        """The row's value under sort key `name` (`key` of its row), made once."""
        if (sorts := self._sorts) is None:
            sorts = self._sorts = {}
        if name not in sorts:
            sorts[name] = key(self.row(*cols))
        return sorts[name]

    def html(self, key: Hashable, render: Callable[[], str]) -> str:
        """The row's cells as a page shows them, rendered by `render` for columns `key` (the
        last rendering kept)."""
        if (done := self._html) is None or done[0] != key:
            done = self._html = (key, render())
        return done[1]

    def serialized(self, format: str) -> bool:
        """Whether the row's JSON (or CSV line) is made already."""
        return (self._csv if format == "csv" else self._json) is not None

    def json(self, cols: tuple[Sequence[str], Sequence[str]], place: Place) -> bytes:
        """The row as the API's JSON shows it, rank and tie group included."""
        if (inner := self._json) is None:
            out = LeaderboardRowOut(**self.row(*cols).__dict__)
            # Every field but the first (rank) and the last two (tied, tie_group), no braces.
            skip = {"rank", "tied", "tie_group"}
            inner = self._json = out.model_dump_json(exclude=skip).encode()[1:-1]
        rank, tied, group = place
        head = b'{"rank":' + _json_int(rank) + b","
        tail = b',"tied":' + (b"true" if tied else b"false") + b',"tie_group":' + _json_int(group)
        return head + inner + tail + b"}"

    def csv(self, cols: tuple[Sequence[str], Sequence[str]], place: Place) -> str:
        """The row as a CSV line, rank and tie group included."""
        if (parts := self._csv) is None:
            parts = self._csv = self._csv_parts(self.row(*cols), *cols)
        before, after = parts
        rank, tied, group = place
        shown = ["" if n is None else str(n) for n in (rank, group)]
        return shown[0] + "," + before + f",{tied},{shown[1]}," + after

    @staticmethod
    def _csv_parts(row: Row, tasks: Sequence[str], conditions: Sequence[str]) -> tuple[str, str]:
        # The cells between rank and tied, and those after the tie group, as the writer would put
        # them in the whole line (several cells: none is quoted for being alone).
        between: list[object] = [
            csv_safe(row.username),
            row.baseline,
            f"{row.score:.4f}",
            f"{row.score_ci_low:.4f}" if row.score_ci_low is not None else "",
            f"{row.score_ci_high:.4f}" if row.score_ci_high is not None else "",
        ]
        after: list[object] = [
            row.submitted_at.isoformat(),
            row.submission_id,
            row.team or "",
            csv_safe(row.team_display_name or ""),
            csv_safe(row.method or ""),
            row.paper_url or "",
            row.code_url or "",
            csv_safe(row.disqualified or ""),
        ]
        for key in ("success_rate", "ci_low", "ci_high"):
            after += [f"{row.tasks[t][key]:.4f}" if t in row.tasks else "" for t in tasks]
        after += [f"{row.conditions[c]:.4f}" if c in row.conditions else "" for c in conditions]
        after.append(";".join(row.environment_differs))
        return _csv_line(between).removesuffix("\r\n"), _csv_line(after)
