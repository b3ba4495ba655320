"""Leaderboards: one row per user (their best public succeeded submission), or per team in
team mode, plus baselines.

Rows live in ``leaderboard_entries``, recomputed by :mod:`server.leaderboard.entries` whenever
something that decides them changes. Each change
bumps the phase's ``leaderboard_version``; readers keep what they read per version: the pages
and challenge pages, pages read by the rank index (`LeaderboardCache`), the API whole boards
(:mod:`server.leaderboard.snapshot`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any, TypeVar

from sqlalchemy import Select, and_, func, or_, select
from sqlalchemy.orm import Session as DB

from server.challenges.charts import ScorePoint
from server.challenges.service import get_challenge, get_phase, suite_of
from server.kit.errors import NotFound
from server.leaderboard.entries import refresh as refresh
from server.leaderboard.entries import summary
from server.models import (
    Challenge,
    LeaderboardEntry,
    Phase,
    State,
    Submission,
    User,
)

V = TypeVar("V")


def board_version(db: DB, *, slug: str, phase: str) -> tuple[int, int]:
    """The id of a challenge's phase and its leaderboard version (one indexed lookup); the
    errors of `get_challenge` and `get_phase` when there is no such phase."""
    found = db.execute(
        select(Phase.id, Phase.leaderboard_version)
        .join(Challenge, Phase.challenge_id == Challenge.id)
        .where(Challenge.slug == slug, Phase.name == phase)
    ).first()
    if found is None:
        get_phase(get_challenge(db, slug=slug), phase)  # raises the precise 404 / 422
        raise NotFound(f"no phase {phase!r}")  # pragma: no cover - raced with a delete
    return found[0], found[1]


def column_order(db: DB, *, slug: str) -> tuple[list[str], list[str]]:
    """The challenge's tasks and conditions in its suite's order: every board's column order."""
    suite = suite_of(get_challenge(db, slug=slug))
    return [t.env_id for t in suite.tasks], [c.name for c in suite.conditions]


def baseline_points(db: DB, *, phase_id: int) -> list[tuple[str, float, datetime]]:
    """The phase's baselines as (label, score, submitted at), best first, for its chart."""
    rows = db.execute(
        select(
            LeaderboardEntry.username,
            LeaderboardEntry.submission_id,
            LeaderboardEntry.score,
            LeaderboardEntry.submitted_at,
        )
        .where(LeaderboardEntry.phase_id == phase_id, LeaderboardEntry.baseline.is_(True))
        .order_by(LeaderboardEntry.score.desc())
    ).all()
    return [(f"baseline {name} #{sid}", score, at) for name, sid, score, at in rows]


def record_points(db: DB, *, phase_id: int) -> list[ScorePoint]:
    """Public succeeded submissions that beat every earlier one: the database keeps the
    running best (a window function), so only the few records travel, however many ran."""
    eligible = and_(
        Submission.phase_id == phase_id,
        Submission.state == State.SUCCEEDED,
        Submission.public.is_(True),
        Submission.hidden.is_(False),
        Submission.baseline.is_(False),
        Submission.score.is_not(None),
    )
    order = (Submission.created_at, Submission.id)
    ranked = (
        select(
            Submission.id,
            Submission.created_at,
            Submission.score,
            User.username,
            func.max(Submission.score).over(order_by=order, rows=(None, -1)).label("before"),
        )
        .join(User, User.id == Submission.user_id)
        .where(eligible)
        .subquery()
    )
    rows = db.execute(
        select(ranked.c.id, ranked.c.created_at, ranked.c.score, ranked.c.username)
        .where((ranked.c.before.is_(None)) | (ranked.c.score > ranked.c.before))
        .order_by(ranked.c.created_at, ranked.c.id)
    ).all()
    return [
        ScorePoint(at=at, score=score, username=name, submission_id=sid)
        for sid, at, score, name in rows
    ]


@dataclass(frozen=True)
class Row:
    rank: int | None  # None for baselines: they are shown for reference, not ranked
    username: str
    submission_id: int
    baseline: bool
    score: float
    submitted_at: datetime
    conditions: dict[str, float]
    tasks: dict[str, dict[str, float]]
    score_ci_low: float | None = None  # the score's 95% interval (None: no results)
    score_ci_high: float | None = None
    tied: bool = False
    """Statistically tied with the ranked row above: their score intervals overlap."""
    team: str | None = None  # the team's name for a team's row (team mode)
    team_display_name: str | None = None
    method: str | None = None
    paper_url: str | None = None
    code_url: str | None = None

    @property
    def participant(self) -> str:
        """Who the row is: the team's display name, or the user's name."""
        return self.team_display_name or self.username

    def in_order(self, *, tasks: Sequence[str], conditions: Sequence[str]) -> Row:
        """This row with its tasks and conditions in the suite's order (unknown ones last)."""
        return replace(
            self,
            tasks=_ordered(self.tasks, tasks),
            conditions=_ordered(self.conditions, conditions),
        )


def _ordered(values: dict[str, V], order: Sequence[str]) -> dict[str, V]:
    known = {name: values[name] for name in order if name in values}
    return known | {name: value for name, value in values.items() if name not in known}


def overlaps(a: tuple[float, float] | None, b: tuple[float, float] | None) -> bool:
    """Whether two intervals share a point (False when either is unknown)."""
    return a is not None and b is not None and a[0] <= b[1] and b[0] <= a[1]


@dataclass(frozen=True)
class Board:
    rows: list[Row]
    total: int


@dataclass(frozen=True)
class BoardMeta:
    total: int
    baselines: list[tuple[float, datetime, int]]  # rank keys of the baseline rows


class LeaderboardCache:
    """Pages of ranked rows per (phase, version, page); a bounded LRU shared by the threads.

    A miss reads just that page by the rank index (and, once per version, the row count and
    the baselines' positions, which fix the ranks of the rows after them), so even the first
    request after a change costs a few indexed queries, not a read of the whole board.
    """

    def __init__(self, size: int = 256) -> None:
        self._pages: OrderedDict[tuple[int, int, int, int], Board] = OrderedDict()
        self._meta: OrderedDict[tuple[int, int], BoardMeta] = OrderedDict()
        self._size = size
        self._lock = threading.Lock()

    def page(self, db: DB, *, phase_id: int, page: int, per_page: int) -> Board:
        """One page of the phase's board in rank order, from the cache when it is current."""
        version = db.scalar(select(Phase.leaderboard_version).where(Phase.id == phase_id)) or 0
        key = (phase_id, version, page, per_page)
        with self._lock:
            if (hit := self._pages.get(key)) is not None:
                self._pages.move_to_end(key)
                return hit
            meta = self._meta.get((phase_id, version))
        if meta is None:
            meta = read_meta(db, phase_id)
        board = Board(rows=read_page(db, phase_id, page, per_page, meta), total=meta.total)
        with self._lock:
            self._meta[(phase_id, version)] = meta
            self._pages[key] = board
            for cache in (self._pages, self._meta):
                while len(cache) > self._size:
                    cache.popitem(last=False)
        return board


_RANK_ORDER = (LeaderboardEntry.score.desc(), LeaderboardEntry.submitted_at, LeaderboardEntry.id)


def read_meta(db: DB, phase_id: int) -> BoardMeta:
    """How many rows the phase's board has, and where its baselines stand."""
    total = db.scalar(
        select(func.count())
        .select_from(LeaderboardEntry)
        .where(LeaderboardEntry.phase_id == phase_id)
    )
    baselines = db.execute(
        select(LeaderboardEntry.score, LeaderboardEntry.submitted_at, LeaderboardEntry.id)
        .where(LeaderboardEntry.phase_id == phase_id, LeaderboardEntry.baseline.is_(True))
        .order_by(*_RANK_ORDER)
    ).all()
    return BoardMeta(total=total or 0, baselines=[(s, t, i) for s, t, i in baselines])


def _ahead(a: tuple[float, datetime, int], b: tuple[float, datetime, int]) -> bool:
    """Whether rank key `a` comes before `b` (higher score, then earlier, then lower id)."""
    return (-a[0], a[1], a[2]) < (-b[0], b[1], b[2])


BOARD_COLUMNS = (
    LeaderboardEntry.id,
    LeaderboardEntry.username,
    LeaderboardEntry.submission_id,
    LeaderboardEntry.baseline,
    LeaderboardEntry.score,
    LeaderboardEntry.submitted_at,
    LeaderboardEntry.team_name,
    LeaderboardEntry.team_display_name,
    LeaderboardEntry.method,
    LeaderboardEntry.paper_url,
    LeaderboardEntry.code_url,
)
"""What a board row shows besides its summary."""


def board_query(phase_id: int, *summary: Any) -> Select[*tuple[Any, ...]]:
    """The phase's rows in rank order, with these summary columns."""
    return (
        select(*BOARD_COLUMNS, *summary)
        .where(LeaderboardEntry.phase_id == phase_id)
        .order_by(*_RANK_ORDER)
    )


Interval = tuple[float, float] | None


def ranked(
    db: DB,
    phase_id: int,
    offset: int,
    entries: Sequence[Any],
    meta: BoardMeta,
    interval_of: Callable[[Any], Interval],
) -> Iterator[tuple[Any, int | None, Interval, bool]]:
    """(entry, rank, score interval, tied) for `entries`, read in rank order from `offset`:
    baselines are not ranked, and a row is tied when its interval overlaps the ranked row's
    above it, on this page or the one before."""
    if not entries:
        return
    first = (entries[0].score, entries[0].submitted_at, entries[0].id)
    rank = offset - sum(1 for b in meta.baselines if _ahead(b, first))
    above = _ranked_before(db, phase_id, first) if rank > 0 else None
    for entry in entries:
        interval = interval_of(entry)
        if entry.baseline:
            yield entry, None, interval, False
            continue
        rank += 1
        yield entry, rank, interval, overlaps(interval, above)
        above = interval


def read_page(db: DB, phase_id: int, page: int, per_page: int, meta: BoardMeta) -> list[Row]:
    """One page of the phase's board in rank order, ranks and ties decided as on every page."""
    offset = (page - 1) * per_page
    query = board_query(phase_id, LeaderboardEntry.summary).offset(offset).limit(per_page)
    entries = db.execute(query).all()
    rows = ranked(
        db,
        phase_id,
        offset,
        entries,
        meta,
        lambda e: interval_of_summary(db, e.summary, e.submission_id),
    )
    return [
        board_row(entry, entry.summary, rank, interval, tied)
        for entry, rank, interval, tied in rows
    ]


def board_row(
    entry: Any, data: dict[str, Any], rank: int | None, interval: Interval, tied: bool
) -> Row:
    """A row as boards show it, from its entry's columns and summary."""
    return Row(
        rank=rank,
        username=entry.username,
        submission_id=entry.submission_id,
        baseline=entry.baseline,
        score=entry.score,
        submitted_at=entry.submitted_at,
        conditions=data.get("conditions", {}),
        tasks=data.get("tasks", {}),
        score_ci_low=interval[0] if interval else None,
        score_ci_high=interval[1] if interval else None,
        tied=tied,
        team=entry.team_name,
        team_display_name=entry.team_display_name,
        method=entry.method,
        paper_url=entry.paper_url,
        code_url=entry.code_url,
    )


def interval_of_summary(db: DB, stored: dict[str, Any], submission_id: int) -> Interval:
    """The score's interval from a row's stored summary; for rows stored before summaries held
    it, measured again from the submission's results (until the row is next refreshed)."""
    if "score_interval" not in stored:
        submission = db.get(Submission, submission_id)
        stored = summary(db, submission=submission) if submission is not None else {}
    found = stored.get("score_interval")
    return (float(found[0]), float(found[1])) if found else None


def _ranked_before(
    db: DB, phase_id: int, key: tuple[float, datetime, int]
) -> tuple[float, float] | None:
    """The score interval of the last ranked (not baseline) row before rank key `key`."""
    score, submitted_at, entry_id = key
    e = LeaderboardEntry
    before = or_(
        e.score > score,
        and_(e.score == score, e.submitted_at < submitted_at),
        and_(e.score == score, e.submitted_at == submitted_at, e.id < entry_id),
    )
    found = db.execute(
        select(e.summary, e.submission_id)
        .where(e.phase_id == phase_id, e.baseline.is_(False), before)
        .order_by(e.score, e.submitted_at.desc(), e.id.desc())
        .limit(1)
    ).first()
    return interval_of_summary(db, found[0], found[1]) if found is not None else None
