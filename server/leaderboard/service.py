"""Leaderboards: one row per user (their best public succeeded submission), or per team in
team mode, plus baselines.

Rows live in ``leaderboard_entries``, recomputed by :mod:`server.standings.entries` whenever
something that decides them changes, per board version (docs/server.md, Re-evaluation). Each
change bumps the phase's ``leaderboard_version`` (a cache key, not the board version);
the API, the leaderboard pages and the challenge pages read whole boards kept per version
(:mod:`server.leaderboard.snapshot`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any, TypeVar

from sqlalchemy import Select, and_, func, select
from sqlalchemy.orm import Session as DB

from evaluator.provenance import differences, environment
from evaluator.results import Environment
from server.challenges.charts import ScorePoint
from server.challenges.service import get_challenge, get_phase, suite_of
from server.kit.errors import NotFound
from server.models import (
    Challenge,
    LeaderboardEntry,
    Phase,
    Submission,
    User,
)
from server.standings.entries import competing, eligible_for, summary

V = TypeVar("V")


def phase_versions(
    db: DB, *, slug: str, phase: str, version: int | None = None
) -> tuple[int, int, int]:
    """The id of a challenge's phase, its leaderboard version (the cache key) and the board
    version to show: `version`, or the current one when None (one indexed lookup); the errors
    of `get_challenge` and `get_phase` when there is no such phase, NotFound when there is no
    published board version `version`."""
    found = db.execute(
        select(Phase.id, Phase.leaderboard_version, Phase.board_version)
        .join(Challenge, Phase.challenge_id == Challenge.id)
        .where(Challenge.slug == slug, Phase.name == phase)
    ).first()
    if found is None:
        get_phase(get_challenge(db, slug=slug), phase)  # raises the precise 404 / 422
        raise NotFound(f"no phase {phase!r}")  # pragma: no cover - raced with a delete
    phase_id, cache, current = found
    if version is None:
        return phase_id, cache, current
    if not 1 <= version <= current:
        raise NotFound(
            f"phase {phase!r} of {slug!r} has board versions 1 to {current}, not {version}"
        )
    return phase_id, cache, version


_COLUMNS: OrderedDict[str, tuple[list[str], list[str]]] = OrderedDict()
_COLUMNS_LOCK = threading.Lock()


def suite_columns(challenge: Challenge) -> tuple[list[str], list[str]]:
    """The tasks and conditions of the challenge's suite, in its order; kept per suite hash,
    as parsing the stored suite costs more than a page's rows."""
    with _COLUMNS_LOCK:
        found = _COLUMNS.get(challenge.suite_hash)
    if found is None:
        suite = suite_of(challenge)
        found = [t.env_id for t in suite.tasks], [c.name for c in suite.conditions]
        with _COLUMNS_LOCK:
            _COLUMNS[challenge.suite_hash] = found
            while len(_COLUMNS) > 64:
                _COLUMNS.popitem(last=False)
    return list(found[0]), list(found[1])


_ENVIRONMENTS: OrderedDict[str, Environment] = OrderedDict()


def suite_environment(challenge: Challenge) -> Environment:
    """The environment the service would evaluate the challenge's suite in now
    (`evaluator.provenance.environment`); kept per suite hash, as `suite_columns` is."""
    with _COLUMNS_LOCK:
        found = _ENVIRONMENTS.get(challenge.suite_hash)
    if found is None:
        suite = suite_of(challenge)
        backends = [t.sim_backend for t in suite.tasks]
        found = environment(suite_sha256=suite.sha256(), sim_backends=backends)
        with _COLUMNS_LOCK:
            _ENVIRONMENTS[challenge.suite_hash] = found
            while len(_ENVIRONMENTS) > 64:
                _ENVIRONMENTS.popitem(last=False)
    return found


def current_version(db: DB, *, phase_id: int) -> int:
    """The board version the phase's board shows now."""
    return db.scalar(select(Phase.board_version).where(Phase.id == phase_id)) or 1


def baseline_points(db: DB, *, phase_id: int) -> list[tuple[str, float, datetime]]:
    """The current board's baselines as (label, score, submitted at), best first, for its
    chart."""
    version = current_version(db, phase_id=phase_id)
    rows = db.execute(
        select(
            LeaderboardEntry.username,
            LeaderboardEntry.submission_id,
            LeaderboardEntry.score,
            LeaderboardEntry.submitted_at,
        )
        .where(
            LeaderboardEntry.phase_id == phase_id,
            LeaderboardEntry.board_version == version,
            LeaderboardEntry.baseline.is_(True),
        )
        .order_by(LeaderboardEntry.score.desc())
    ).all()
    return [(f"baseline {name} #{sid}", score, at) for name, sid, score, at in rows]


def record_points(db: DB, *, phase_id: int) -> list[ScorePoint]:
    """Public succeeded submissions that beat every earlier one: the database keeps the
    running best (a window function), so only the few records travel, however many ran."""
    version = current_version(db, phase_id=phase_id)
    records = and_(*eligible_for(phase_id, version), *competing())
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
        .where(records)
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
    rank: int | None  # None for baselines and disqualified rows: they are not ranked
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
    """In the tie group of the ranked row above: the paired test does not separate them."""
    tie_group: int | None = None
    """1, 2, ... down the board: neighbours not significantly different share a group
    (docs/metrics.md, "Paired significance"); None for baselines."""
    team: str | None = None  # the team's name for a team's row (team mode)
    team_display_name: str | None = None
    method: str | None = None
    paper_url: str | None = None
    code_url: str | None = None
    environment_differs: tuple[str, ...] = ()
    """What of its evaluation environment differs from the service's current one (none:
    the same, or not known): docs/metrics.md, Provenance."""
    disqualified: str | None = None
    """Why the organizers disqualified it (then it is unranked, after the ranked rows); None:
    it was not."""

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


@dataclass(frozen=True)
class Board:
    rows: list[Row]
    total: int


_RANK_ORDER = (LeaderboardEntry.score.desc(), LeaderboardEntry.submitted_at, LeaderboardEntry.id)


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


def board_query(phase_id: int, board_version: int, *summary: Any) -> Select[*tuple[Any, ...]]:
    """The rows of this version of the phase's board in rank order, with these summary
    columns."""
    return (
        select(*BOARD_COLUMNS, *summary)
        .where(
            LeaderboardEntry.phase_id == phase_id, LeaderboardEntry.board_version == board_version
        )
        .order_by(*_RANK_ORDER)
    )


Interval = tuple[float, float] | None


def board_row(
    entry: Any,
    data: dict[str, Any],
    rank: int | None,
    interval: Interval,
    current: Environment | None = None,
) -> Row:
    """A row as boards show it, from its entry's columns and summary; marked where its
    environment differs from `current` (the suite's now)."""
    recorded = data.get("environment") or {}
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
        team=entry.team_name,
        team_display_name=entry.team_display_name,
        method=entry.method,
        paper_url=entry.paper_url,
        code_url=entry.code_url,
        environment_differs=tuple(differences(recorded, current)) if current else (),
        disqualified=data.get("disqualified"),
    )


def interval_of_summary(db: DB, stored: dict[str, Any], submission_id: int) -> Interval:
    """The score's interval from a row's stored summary; for rows stored before summaries held
    it, measured again from the submission's results (until the row is next refreshed)."""
    if "score_interval" not in stored:
        submission = db.get(Submission, submission_id)
        stored = summary(db, submission=submission) if submission is not None else {}
    found = stored.get("score_interval")
    return (float(found[0]), float(found[1])) if found else None
