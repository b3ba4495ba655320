"""The submission state machine: which state may follow which, and the one way to move.

Every state change is one conditional ``UPDATE ... WHERE state IN (...) AND attempt = ...``:
of two workers racing the same submission exactly one changes it, and the loser learns so from
the row count. Each change is recorded in ``transitions`` with its time and reason. Work for
the queue is written to the ``outbox`` in the same transaction and sent after the commit.
"""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from typing import Any

from sqlalchemy import update
from sqlalchemy.orm import Session as DB

from server.models import FINAL_STATES, Cause, Outbox, State, Submission, Transition, utcnow
from server.standings.entries import refresh
from server.standings.versions import published_after_end
from server.submissions.changes import changed

# Which states each state may move to (re-run, a new attempt, is separate: final -> queued).
ALLOWED: dict[State, frozenset[State]] = {
    State.QUEUED: frozenset({State.LAUNCHING, State.CANCELLED, State.ERROR}),
    State.LAUNCHING: frozenset(
        {State.RUNNING, State.CANCELLED, State.ERROR, State.FAILED, State.TIMED_OUT}
    ),
    State.RUNNING: frozenset(
        {State.SUCCEEDED, State.FAILED, State.ERROR, State.CANCELLED, State.TIMED_OUT}
    ),
}


def sources_from(states: Iterable[State], target: State) -> list[State]:
    """The states among `states` that may move to `target`."""
    return [s for s in states if target in ALLOWED.get(s, frozenset())]


def transition(
    db: DB,
    submission_id: int,
    attempt: int,
    to: State,
    reason: str,
    *,
    now: datetime | None = None,
    cause: Cause | None = None,
    **values: Any,
) -> bool:
    """Move the submission to `to` if its current attempt is in a state that allows it;
    `cause` is recorded with the transition, `values` set on the submission.

    Returns False (and changes nothing) when another actor got there first.
    """
    now = now or utcnow()
    sources = sources_from(ALLOWED, to)
    if to == State.RUNNING:
        values.setdefault("started_at", now)
        values.setdefault("heartbeat_at", now)
    if to.final:
        values.setdefault("finished_at", now)
    previous: State | None = None
    for source in sources:  # one atomic conditional update per possible source state
        result = db.execute(
            update(Submission)
            .where(
                Submission.id == submission_id,
                Submission.attempt == attempt,
                Submission.state == source,
            )
            .values(state=to, reason=reason[:2000], updated_at=now, **values)
            .execution_options(synchronize_session=False)
        )
        if result.rowcount == 1:  # type: ignore[attr-defined]
            previous = source
            break
    if previous is None:
        return False
    db.add(
        Transition(
            submission_id=submission_id,
            attempt=attempt,
            from_state=previous,
            to_state=to,
            reason=reason[:2000],
            cause=cause,
            at=now,
        )
    )
    db.flush()
    changed(db, submission_id)
    if to.final:
        published_after_end(db, submission_id=submission_id)
    return True


def queued_first(db: DB, submission: Submission, reason: str, *, now: datetime) -> None:
    """A new submission (flushed, QUEUED at attempt 1; or a re-evaluation's copy): its first
    transition, and the outbox row that wakes a worker once the transaction commits."""
    db.add(
        Transition(
            submission_id=submission.id,
            attempt=1,
            from_state=None,
            to_state=State.QUEUED,
            reason=reason[:2000],
            at=now,
        )
    )
    db.add(Outbox(submission_id=submission.id, attempt=1, created_at=now))


def new_attempt(
    db: DB,
    submission: Submission,
    reason: str,
    *,
    from_states: frozenset[State] = FINAL_STATES,
    now: datetime | None = None,
) -> bool:
    """Queue an ended submission again as attempt N+1 (its old results stay with attempt N).

    False when it is not in one of `from_states` any more (someone else acted first).
    """
    now = now or utcnow()
    old, previous = submission.attempt, submission.state
    result = db.execute(
        update(Submission)
        .where(
            Submission.id == submission.id,
            Submission.attempt == old,
            Submission.state.in_(from_states),
        )
        .values(
            attempt=old + 1,
            state=State.QUEUED,
            reason=reason,
            updated_at=now,
            started_at=None,
            finished_at=None,
            heartbeat_at=None,
            deadline_at=None,
            score=None,
            result=None,
            log_tail="",
            progress=None,
        )
        .execution_options(synchronize_session=False)
    )
    if result.rowcount != 1:  # type: ignore[attr-defined]
        return False
    db.add(
        Transition(
            submission_id=submission.id,
            attempt=old + 1,
            from_state=previous,
            to_state=State.QUEUED,
            reason=reason,
            at=now,
        )
    )
    db.add(Outbox(submission_id=submission.id, attempt=old + 1, created_at=now))
    db.flush()
    changed(db, submission.id)
    db.refresh(submission)
    refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    return True
