"""What the worker reports: state changes, progress and results of one (submission, attempt).

Idempotent: reporting the same final state twice is a no-op, results of an attempt replace any
earlier copy of that attempt's results, and a report about an attempt that is no longer the
submission's current one is refused (`Conflict`), so a late worker cannot overwrite a re-run.
"""

from __future__ import annotations

import re
from datetime import timedelta
from typing import Any, TypeVar

from sqlalchemy import delete, update
from sqlalchemy.orm import Session as DB

from evaluator.results import EvaluationResult, ran
from internal_api.schemas import LOG_TAIL_LIMIT, ErrorCause
from server.kit.errors import Conflict, Invalid, NotFound
from server.models import (
    Cause,
    EpisodeResultRow,
    State,
    Submission,
    TaskResultRow,
    utcnow,
)
from server.standings.entries import refresh
from server.submissions.changes import changed
from server.submissions.reconcile import end_lost
from server.submissions.states import transition

_UNSTORABLE = re.compile("[\x00\ud800-\udfff]")
T = TypeVar("T")


def storable_data(value: T) -> T:
    """Text from a worker (a policy's log, its reasons, a result) with what a database cannot
    hold, NUL and lone surrogates, replaced by U+FFFD; the rest, control characters included,
    is kept as the policy wrote it."""
    if isinstance(value, str):
        return _UNSTORABLE.sub("\ufffd", value)  # type: ignore[return-value]
    if isinstance(value, dict):
        return {storable_data(k): storable_data(v) for k, v in value.items()}  # type: ignore[return-value]
    if isinstance(value, list):
        return [storable_data(v) for v in value]  # type: ignore[return-value]
    return value


def _current(db: DB, submission_id: int, attempt: int) -> Submission:
    submission = db.get(Submission, submission_id, populate_existing=True)
    if submission is None:
        raise NotFound(f"no submission {submission_id}")
    if submission.attempt != attempt:
        raise Conflict(
            f"attempt {attempt} of submission {submission_id} is stale "
            f"(current attempt: {submission.attempt})"
        )
    return submission


def report_state(db: DB, submission_id: int, attempt: int, state: State, reason: str) -> bool:
    """A non-final state change (launching, running). False when it no longer applies."""
    if state.final:
        raise Invalid("final states are reported with their results (report_final)")
    reason = storable_data(reason)
    submission = _current(db, submission_id, attempt)
    if submission.state == state:
        return True
    return transition(db, submission_id, attempt, state, reason)


def report_running(
    db: DB, submission_id: int, attempt: int, *, reason: str, deadline_s: float
) -> bool:
    """`launching` -> `running`, with the deadline after which the reconciler times it out.
    False when the attempt no longer runs (cancelled meanwhile)."""
    if not report_state(db, submission_id, attempt, State.RUNNING, reason):
        return False
    db.execute(
        update(Submission)
        .where(Submission.id == submission_id, Submission.attempt == attempt)
        .values(deadline_at=utcnow() + timedelta(seconds=deadline_s))
        .execution_options(synchronize_session=False)
    )
    return True


def report_progress(
    db: DB, submission_id: int, attempt: int, progress: dict[str, Any] | None
) -> bool:
    """Heartbeat and progress of a running attempt (None: a heartbeat only); False if it is
    not running any more."""
    _current(db, submission_id, attempt)
    now = utcnow()
    values: dict[str, Any] = {"heartbeat_at": now, "updated_at": now}
    if progress is not None:
        values["progress"] = storable_data(progress)
    result = db.execute(
        update(Submission)
        .where(
            Submission.id == submission_id,
            Submission.attempt == attempt,
            Submission.state.in_([State.LAUNCHING, State.RUNNING]),
        )
        .values(**values)
        .execution_options(synchronize_session=False)
    )
    applied = bool(result.rowcount == 1)  # type: ignore[attr-defined]
    if applied and progress is not None:  # a bare heartbeat changes nothing a view shows
        changed(db, submission_id)
    return applied


ENDED_ELSEWHERE = frozenset({State.CANCELLED, State.TIMED_OUT})
"""Final states the server gives a running attempt itself; its worker reports what ran after."""


def report_final(
    db: DB,
    submission_id: int,
    attempt: int,
    state: State,
    reason: str,
    *,
    result: EvaluationResult | None = None,
    log_tail: str = "",
    cause: ErrorCause | None = None,
) -> bool:
    """End an attempt. True when this call (or an identical earlier one) ended it so. An
    `error` the cluster caused is ours: no quota, and the submission runs again once; one the
    configuration caused is ours too, and stays `error` (it would fail again)."""
    if not state.final:
        raise Invalid(f"{state.value} is not a final state")
    if state == State.SUCCEEDED and result is None:
        raise Invalid("a succeeded submission needs its result document")
    submission = _current(db, submission_id, attempt)
    if result is not None:
        result = EvaluationResult.model_validate(storable_data(result.model_dump(mode="json")))
    if submission.state.final:
        # Idempotent repeat of the same report; any other final state already won. What ran
        # of an attempt ended elsewhere (a cancel, the reconciler's timeout) comes after the
        # end, from the worker that stopped it: kept once, the state and reason unchanged.
        if (
            submission.state == state
            and state in ENDED_ELSEWHERE
            and result is not None
            and submission.result is None
        ):
            _store_results(db, submission, result)
            submission.result = result.model_dump(mode="json")
            changed(db, submission_id)
        return submission.state == state
    reason, log_tail = storable_data(reason), storable_data(log_tail[-LOG_TAIL_LIMIT:])
    values: dict[str, Any] = {"log_tail": log_tail}
    if cause is not None:
        if state != State.ERROR:
            raise Invalid(f"a cause goes only with error, not {state.value}")
        if cause == ErrorCause.CONFIGURATION:  # ours, but it would fail again until configured
            return transition(
                db, submission_id, attempt, state, reason, cause=Cause.CONFIGURATION, **values
            )
        return (
            end_lost(db, submission, cause=Cause(cause.value), detail=reason, **values) is not None
        )
    if result is not None:
        _store_results(db, submission, result)
        values["result"] = result.model_dump(mode="json")
        if state == State.SUCCEEDED:
            values["score"] = result.score
    if not transition(db, submission_id, attempt, state, reason, **values):
        return False
    db.refresh(submission)
    if state == State.SUCCEEDED:
        refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    return True


def _store_results(db: DB, submission: Submission, result: EvaluationResult) -> None:
    db.execute(
        delete(TaskResultRow).where(
            TaskResultRow.submission_id == submission.id,
            TaskResultRow.attempt == submission.attempt,
        )
    )
    for condition in result.conditions:
        for task in condition.tasks:
            episodes = [episode for episode in task.episodes if ran(episode)]
            row = TaskResultRow(
                submission_id=submission.id,
                attempt=submission.attempt,
                condition=condition.name,
                env_id=task.env_id,
                episodes=task.episodes_planned,
                episodes_ran=len(episodes),
                successes=task.successes,
                success_rate=task.success_rate,
                ci_low=task.ci_low,
                ci_high=task.ci_high,
                mean_steps=task.mean_steps,
            )
            db.add(row)
            db.flush()
            db.add_all(
                EpisodeResultRow(
                    task_result_id=row.id,
                    index=episode.index,
                    seed=episode.seed,
                    success_once=episode.success_once,
                    success_at_end=episode.success_at_end,
                    steps=episode.steps,
                    episode_return=episode.episode_return,
                    wall_time_s=episode.wall_time_s,
                    invalid_actions=episode.invalid_actions,
                    clipped_actions=episode.clipped_actions,
                    failure=episode.failure_reason,
                )
                for episode in episodes
            )
    db.flush()


def check_running(db: DB, *, submission_id: int, attempt: int) -> None:
    """NotFound or Conflict unless `attempt` is the submission's current one and still runs
    (what a worker may store videos for)."""
    submission = _current(db, submission_id, attempt)
    if submission.state not in (State.LAUNCHING, State.RUNNING):
        raise Conflict(f"attempt {attempt} of submission {submission_id} has ended")


def current_state(db: DB, *, submission_id: int) -> State:
    """The submission's state as the database has it now (what a report's answer carries)."""
    submission = db.get(Submission, submission_id, populate_existing=True)
    if submission is None:
        raise NotFound(f"no submission {submission_id}")
    return submission.state
