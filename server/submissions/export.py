"""Every submission of a challenge with its result, for an organizer's own analysis: one row
per submission, as CSV or JSON, streamed in batches read by id so that neither the server nor
the command line holds a large challenge whole (docs/server.md, Organizer tools)."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Iterator
from datetime import datetime
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.challenges.service import suite_of
from server.kit.spreadsheets import csv_safe
from server.models import Challenge, Phase, Submission, TaskResultRow, Team, Transition, User
from server.submissions.service import condition_means, task_outcome

ExportFormat = Literal["csv", "json"]
BATCH = 500
"""Submissions read per query."""

_FIRST = ["submission_id", "username", "team", "phase", "board_version", "reevaluation_of"]
_FIRST += ["state", "reason", "cause", "attempt", "score"]
_LAST = ["hidden", "disqualified", "moderation_reason", "baseline", "public", "post_deadline"]
_LAST += ["created_at", "started_at", "finished_at", "pinned_image"]
_TEXT = frozenset({"username", "team", "reason", "moderation_reason"})
"""Cells whose text a participant or an organizer chose: defused for spreadsheets in CSV."""


def columns_of(challenge: Challenge) -> list[str]:
    """The export's columns: the suite's conditions' means ("condition NAME") after the score."""
    conditions = [f"condition {c.name}" for c in suite_of(challenge).conditions]
    return [*_FIRST, *conditions, *_LAST]


def export_rows(db: DB, *, challenge: Challenge, phase: Phase | None) -> Iterator[dict[str, Any]]:
    """Every submission of the challenge (of `phase` only, if given), by id, as a row: its
    current attempt's state, reason, error cause, score and condition means."""
    query = (
        select(Submission, User.username, Team.name, Phase.name)
        .join(User, User.id == Submission.user_id)
        .join(Phase, Phase.id == Submission.phase_id)
        .outerjoin(Team, Team.id == Submission.team_id)
        .where(Submission.challenge_id == challenge.id)
        .order_by(Submission.id)
        .limit(BATCH)
    )
    if phase is not None:
        query = query.where(Submission.phase_id == phase.id)
    after = 0
    while chunk := db.execute(query.where(Submission.id > after)).all():
        submissions = [row[0] for row in chunk]
        tasks, causes = _results(db, submissions)
        for s, username, team, phase_name in chunk:
            yield _row(s, username, team, phase_name, tasks.get(s.id, []), causes.get(s.id))
        after = submissions[-1].id
        for s in submissions:  # what was read is not kept: the session's map stays small
            db.expunge(s)


def _results(
    db: DB, submissions: list[Submission]
) -> tuple[dict[int, list[TaskResultRow]], dict[int, str | None]]:
    """The current attempts' task rows and the cause of their last transition, by id."""
    attempt = {s.id: s.attempt for s in submissions}
    tasks: dict[int, list[TaskResultRow]] = {}
    found = db.scalars(
        select(TaskResultRow)
        .where(TaskResultRow.submission_id.in_(attempt))
        .order_by(TaskResultRow.id)
        .execution_options(populate_existing=True)
    )
    for row in found:
        if row.attempt == attempt[row.submission_id]:
            tasks.setdefault(row.submission_id, []).append(row)
        db.expunge(row)
    causes: dict[int, str | None] = {}
    ends = db.execute(
        select(Transition.submission_id, Transition.attempt, Transition.cause)
        .where(Transition.submission_id.in_(attempt))
        .order_by(Transition.id)
    )
    for sid, number, cause in ends:
        if number == attempt[sid]:
            causes[sid] = cause.value if cause is not None else None
    return tasks, causes


def _when(at: datetime | None) -> str | None:
    return at.isoformat() if at is not None else None


def _row(
    s: Submission,
    username: str,
    team: str | None,
    phase: str,
    tasks: list[TaskResultRow],
    cause: str | None,
) -> dict[str, Any]:
    means = condition_means([task_outcome(row) for row in tasks])
    return {
        "submission_id": s.id,
        "username": username,
        "team": team,
        "phase": phase,
        "board_version": s.board_version,
        "reevaluation_of": s.reevaluation_of,
        "state": s.state.value,
        "reason": s.reason,
        "cause": cause,
        "attempt": s.attempt,
        "score": s.score,
        **{f"condition {name}": value for name, value in means.items()},
        "hidden": s.hidden,
        "disqualified": s.disqualified,
        "moderation_reason": s.moderation_reason,
        "baseline": s.baseline,
        "public": s.public,
        "post_deadline": s.post_deadline,
        "created_at": _when(s.created_at),
        "started_at": _when(s.started_at),
        "finished_at": _when(s.finished_at),
        "pinned_image": s.pinned_image,
    }


def as_csv(rows: Iterable[dict[str, Any]], columns: list[str]) -> Iterator[str]:
    """The rows as CSV text, a line at a time, the header first (a condition the suite no
    longer has is left out; one a submission lacks is empty)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)

    def line(cells: Iterable[object]) -> str:
        buffer.seek(0)
        buffer.truncate()
        writer.writerow(cells)
        return buffer.getvalue()

    yield line(columns)
    for row in rows:
        yield line(_cell(name, row.get(name)) for name in columns)


def _cell(name: str, value: object) -> object:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4f}"
    return csv_safe(value) if name in _TEXT and isinstance(value, str) else value


def as_json(rows: Iterable[dict[str, Any]]) -> Iterator[str]:
    """The rows as one JSON array, a row at a time."""
    yield "["
    for n, row in enumerate(rows):
        yield ("," if n else "") + json.dumps(row, separators=(",", ":"))
    yield "]\n"


def export_text(
    db: DB, *, challenge: Challenge, phase: Phase | None, format: ExportFormat
) -> Iterator[str]:
    """The export as text, produced as it is read."""
    rows = export_rows(db, challenge=challenge, phase=phase)
    return as_csv(rows, columns_of(challenge)) if format == "csv" else as_json(rows)
