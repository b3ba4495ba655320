"""How an attempt ends, whichever executor ran it: the state, the reason, the stored result."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from evaluator.results import EvaluationResult
from server.kit.errors import Conflict
from server.models import State, Submission
from server.submissions.reports import report_final, report_state


def start_running(
    sessions: sessionmaker[Session],
    submission_id: int,
    attempt: int,
    deadline: datetime,
    reason: str = "evaluating",
) -> bool:
    """`launching` → `running` with the deadline the reconciler enforces; False if the attempt
    is no longer ours to run (cancelled, or replaced by a re-run)."""
    with sessions.begin() as db:
        if not report_state(db, submission_id, attempt, State.RUNNING, reason):
            return False
        db.execute(
            update(Submission)
            .where(Submission.id == submission_id, Submission.attempt == attempt)
            .values(deadline_at=deadline)
        )
    return True


def conclude(
    sessions: sessionmaker[Session],
    submission_id: int,
    attempt: int,
    result: EvaluationResult,
    *,
    log_tail: str = "",
    detail: str | None = None,
) -> State | None:
    """End the attempt as its result document says: succeeded with a score, or failed (or
    timed out) with the abort's reason; `detail` adds what the platform saw of the policy."""
    abort = result.abort
    if result.status == "aborted" and abort is not None:
        state = State.TIMED_OUT if abort.kind == "budget_exhausted" else State.FAILED
        reason = (
            abort.reason if not detail or detail in abort.reason else f"{abort.reason}; {detail}"
        )
        return finish(
            sessions,
            submission_id,
            attempt,
            state,
            reason,
            result=result,
            log_tail=abort.log_tail or log_tail,
        )
    return finish(
        sessions,
        submission_id,
        attempt,
        State.SUCCEEDED,
        f"score {result.score:.3f}",
        result=result,
    )


def finish(
    sessions: sessionmaker[Session],
    submission_id: int,
    attempt: int,
    state: State,
    reason: str,
    *,
    result: EvaluationResult | None = None,
    log_tail: str = "",
) -> State | None:
    """Record the final state (idempotent); returns the state the submission is in now."""
    try:
        with sessions.begin() as db:
            report_final(
                db, submission_id, attempt, state, reason, result=result, log_tail=log_tail
            )
    except Conflict:
        pass  # a re-run replaced this attempt
    return final_state(sessions, submission_id)


def final_state(sessions: sessionmaker[Session], submission_id: int) -> State | None:
    """The submission's state as stored (None if it does not exist)."""
    with sessions() as db:
        submission = db.get(Submission, submission_id)
        return submission.state if submission is not None else None
