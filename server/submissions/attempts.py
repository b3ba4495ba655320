"""A submission run more than once (an organizer's re-run, the reconciler's retry): each
attempt's per-task results side by side, with how each attempt ended (docs/server.md,
Organizer tools)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.models import State, Submission, TaskResultRow
from server.submissions.service import TaskOutcome, task_outcome, transitions_of

Task = tuple[str, str]
"""A condition and a task (env id): a row of the comparison."""


@dataclass(frozen=True)
class Attempt:
    """One attempt: how it stands or ended, and its results by task."""

    number: int
    state: State
    """Its last state: its end for every attempt but a current one that still runs."""
    reason: str
    at: datetime
    results: dict[Task, TaskOutcome]


@dataclass(frozen=True)
class Attempts:
    """Every attempt of a submission, in order, and the tasks any of them has results for."""

    attempts: list[Attempt]
    tasks: list[Task]


def attempts_of(db: DB, *, submission: Submission) -> Attempts | None:
    """The attempts side by side; None for a submission that ran once."""
    if submission.attempt < 2:
        return None
    last = {t.attempt: t for t in transitions_of(db, submission_id=submission.id)}
    rows = db.scalars(
        select(TaskResultRow)
        .where(TaskResultRow.submission_id == submission.id)
        .order_by(TaskResultRow.attempt, TaskResultRow.id)
    ).all()
    results: dict[int, dict[Task, TaskOutcome]] = {}
    tasks: dict[Task, None] = {}  # in the order first reported
    for row in rows:
        key = (row.condition, row.env_id)
        results.setdefault(row.attempt, {})[key] = task_outcome(row)
        tasks[key] = None
    attempts = [
        Attempt(
            number=number,
            state=end.to_state,
            reason=end.reason,
            at=end.at,
            results=results.get(number, {}),
        )
        for number, end in sorted(last.items())
    ]
    return Attempts(attempts=attempts, tasks=list(tasks))
