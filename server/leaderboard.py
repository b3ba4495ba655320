"""Leaderboards: one row per user (their best public succeeded submission) plus baselines.

Rows live in ``leaderboard_entries``, recomputed for one (phase, user) whenever something that
decides them changes (a result, a re-run, hiding, visibility, the baseline flag). Each change
bumps the phase's ``leaderboard_version``; readers cache the ranked list per version, so a
leaderboard request costs one indexed lookup of the version when nothing changed.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session as DB

from server.models import LeaderboardEntry, Phase, State, Submission, TaskResultRow, User


def refresh(db: DB, phase_id: int, user_id: int) -> None:
    """Recompute a user's rows in a phase's leaderboard (call inside the changing transaction)."""
    # Serialise refreshes of one user: the unique (phase, owner) row must not be raced.
    db.execute(select(User.id).where(User.id == user_id).with_for_update())
    db.execute(
        delete(LeaderboardEntry).where(
            LeaderboardEntry.phase_id == phase_id, LeaderboardEntry.user_id == user_id
        )
    )
    eligible = db.scalars(
        select(Submission)
        .where(
            Submission.phase_id == phase_id,
            Submission.user_id == user_id,
            Submission.state == State.SUCCEEDED,
            Submission.public.is_(True),
            Submission.hidden.is_(False),
            Submission.score.is_not(None),
        )
        .order_by(Submission.score.desc(), Submission.created_at, Submission.id)
    ).all()
    best_regular = next((s for s in eligible if not s.baseline), None)
    chosen = [s for s in eligible if s.baseline]
    if best_regular is not None:
        chosen.append(best_regular)
    for submission in chosen:
        assert submission.score is not None
        db.add(
            LeaderboardEntry(
                phase_id=phase_id,
                submission_id=submission.id,
                user_id=user_id,
                owner_key=None if submission.baseline else user_id,
                baseline=submission.baseline,
                score=submission.score,
                submitted_at=submission.created_at,
                username=submission.user.username,
                summary=summary(db, submission),
            )
        )
    db.execute(
        update(Phase)
        .where(Phase.id == phase_id)
        .values(leaderboard_version=Phase.leaderboard_version + 1)
    )
    db.flush()


def summary(db: DB, submission: Submission) -> dict[str, Any]:
    """Per-condition scores and per-task success with intervals, for the leaderboard row."""
    rows = db.scalars(
        select(TaskResultRow)
        .where(
            TaskResultRow.submission_id == submission.id,
            TaskResultRow.attempt == submission.attempt,
        )
        .order_by(TaskResultRow.id)
    ).all()
    conditions: dict[str, list[float]] = {}
    tasks: dict[str, dict[str, float]] = {}
    first: str | None = None
    for row in rows:
        first = first or row.condition
        conditions.setdefault(row.condition, []).append(row.success_rate)
        if row.condition == first:
            tasks[row.env_id] = {
                "success_rate": row.success_rate,
                "ci_low": row.ci_low,
                "ci_high": row.ci_high,
            }
    return {
        "conditions": {name: sum(v) / len(v) for name, v in conditions.items()},
        "tasks": tasks,
    }


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


class LeaderboardCache:
    """Ranked rows per (phase, version); a bounded LRU shared by the API's threads."""

    def __init__(self, size: int = 64) -> None:
        self._rows: OrderedDict[tuple[int, int], list[Row]] = OrderedDict()
        self._size = size
        self._lock = threading.Lock()

    def rows(self, db: DB, phase: Phase) -> list[Row]:
        version = db.scalar(select(Phase.leaderboard_version).where(Phase.id == phase.id))
        key = (phase.id, version or 0)
        with self._lock:
            if key in self._rows:
                self._rows.move_to_end(key)
                return self._rows[key]
        rows = ranked(db, phase.id)
        with self._lock:
            self._rows[key] = rows
            while len(self._rows) > self._size:
                self._rows.popitem(last=False)
        return rows


def ranked(db: DB, phase_id: int) -> list[Row]:
    entries = db.execute(
        select(
            LeaderboardEntry.username,
            LeaderboardEntry.submission_id,
            LeaderboardEntry.baseline,
            LeaderboardEntry.score,
            LeaderboardEntry.submitted_at,
            LeaderboardEntry.summary,
        )
        .where(LeaderboardEntry.phase_id == phase_id)
        .order_by(LeaderboardEntry.score.desc(), LeaderboardEntry.submitted_at, LeaderboardEntry.id)
    ).all()
    rows: list[Row] = []
    rank = 0
    for username, submission_id, baseline, score, submitted_at, data in entries:
        if not baseline:
            rank += 1
        rows.append(
            Row(
                rank=None if baseline else rank,
                username=username,
                submission_id=submission_id,
                baseline=baseline,
                score=score,
                submitted_at=submitted_at,
                conditions=data.get("conditions", {}),
                tasks=data.get("tasks", {}),
            )
        )
    return rows
