"""The reconciler: compares what the database says with what is really going on, and decides.

A worker asks for a pass periodically (Celery beat on its own queue, or the embedded worker's
timer), through the internal API. Each pass:
- times out runs past their deadline (`timed_out`; the running worker sees it and stops);
- ends runs whose worker stopped reporting (`error`), and queues them once more as a new
  attempt, since that was our fault; a second loss of the same submission stays `error`;
- sends what the outbox still holds, and wakes workers for queued submissions that have
  waited too long (a lost message);
- answers which attempts are active, so the worker removes containers and Jobs of the others.
Before the pass, the worker looks at the silent attempts (`silent`): a Kubernetes Job that
still runs gets a new watcher and a heartbeat instead of being thrown away.
Wake-ups are hints; this pass is what guarantees every submission ends.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import ColumnElement, func, select
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import AttemptRef, ReconcileOut
from server.kit.settings import Settings
from server.models import ACTIVE_STATES, Cause, State, Submission, Transition, utcnow
from server.submissions.outbox import Dispatcher, WorkQueue
from server.submissions.states import new_attempt, transition

log = logging.getLogger(__name__)

LOST_CAUSES = frozenset({Cause.WORKER_LOST, Cause.WORKER_RESTARTED, Cause.CLUSTER})
"""Causes that are ours, not the policy's: the attempt runs again, once per submission (a
second loss may be the policy's doing: a worker it crashes, a node it exhausts)."""
_WHAT = {
    Cause.WORKER_LOST: "the worker evaluating it stopped responding",
    Cause.WORKER_RESTARTED: "the worker evaluating it restarted",
    Cause.CLUSTER: "the cluster stopped the evaluation",
    Cause.STOPPED: "interrupted: the service was stopped",
}
_AGAIN = {Cause.STOPPED: "interrupted: the service was stopped; queued again"}
"""The re-queued attempt's reason (what its owner reads while it waits), where `<what>:
running it again` would not be true: after a stop it runs when the service starts again."""


@dataclass(frozen=True)
class Timeouts:
    heartbeat: timedelta = timedelta(minutes=3)
    """A running attempt whose worker has not reported for this long is lost."""
    launch: timedelta = timedelta(minutes=15)
    """A launching attempt (pulling an image) that has not started running by then is lost."""
    requeue: timedelta = timedelta(minutes=2)
    """A queued submission untouched this long gets a fresh wake-up message."""


def timeouts_of(settings: Settings) -> Timeouts:
    """The timeouts this service is configured with (`MANIEVAL_HEARTBEAT_TIMEOUT_S`)."""
    return Timeouts(heartbeat=timedelta(seconds=settings.heartbeat_timeout_s))


def _silent_running(timeouts: Timeouts, now: datetime) -> ColumnElement[bool]:
    return (Submission.state == State.RUNNING) & (
        func.coalesce(Submission.heartbeat_at, Submission.updated_at) < now - timeouts.heartbeat
    )


def _lost(timeouts: Timeouts, now: datetime) -> ColumnElement[bool]:
    stale_launch = (Submission.state == State.LAUNCHING) & (
        Submission.updated_at < now - timeouts.launch
    )
    return _silent_running(timeouts, now) | stale_launch


def _past_deadline(now: datetime) -> ColumnElement[bool]:
    return (
        Submission.state.in_([State.LAUNCHING, State.RUNNING])
        & Submission.deadline_at.is_not(None)
        & (Submission.deadline_at < now)
    )


def stuck(timeouts: Timeouts, now: datetime) -> ColumnElement[bool]:
    """Attempts the reconciler ends at its next pass: past their deadline, running with no
    heartbeat within the timeout, or launching for longer than the launch timeout (what an
    organizer's "re-run the stuck" acts on at once: `server.submissions.moderation`)."""
    return _past_deadline(now) | _lost(timeouts, now)


def silent(
    db: Session, *, timeouts: Timeouts = Timeouts(), now: datetime | None = None
) -> list[AttemptRef]:
    """Running attempts whose worker has not reported within the heartbeat timeout."""
    now = now or utcnow()
    rows = db.execute(
        select(Submission.id, Submission.attempt).where(_silent_running(timeouts, now))
    ).all()
    return [AttemptRef(submission_id=sid, attempt=attempt) for sid, attempt in rows]


def reconcile(
    sessions: sessionmaker[Session],
    work: WorkQueue,
    *,
    timeouts: Timeouts = Timeouts(),
    now: datetime | None = None,
) -> ReconcileOut:
    """One pass; see the module's docstring."""
    now = now or utcnow()
    out = ReconcileOut()
    with sessions() as db:
        _time_out(db, now, out)
        for s in db.scalars(select(Submission).where(_lost(timeouts, now))):
            requeued = end_lost(db, s, cause=Cause.WORKER_LOST, now=now)
            if requeued is not None:
                out.lost.append(s.id)
                if requeued:
                    out.requeued.append(s.id)
            db.commit()
        waiting = db.scalar(
            select(func.count())
            .select_from(Submission)
            .where(Submission.state == State.QUEUED, Submission.updated_at < now - timeouts.requeue)
        )
        out.active = [
            AttemptRef(submission_id=sid, attempt=attempt)
            for sid, attempt in db.execute(
                select(Submission.id, Submission.attempt).where(Submission.state.in_(ACTIVE_STATES))
            )
        ]
    Dispatcher(sessions, work).dispatch()  # outbox rows no server sent (e.g. re-queued above)
    for _ in range(waiting or 0):
        try:
            work.enqueue(0, 0)  # a wake-up: the worker claims the fairest queued submission
            out.woken += 1
        except Exception:
            log.exception("could not send a wake-up; the next pass will try again")
            break
    if out.timed_out or out.lost:
        log.info(
            "reconciled: timed out %s, lost %s, requeued %s", out.timed_out, out.lost, out.requeued
        )
    return out


def _time_out(db: Session, now: datetime, out: ReconcileOut) -> None:
    for s in db.scalars(select(Submission).where(_past_deadline(now))):
        reason = "the evaluation exceeded its time budget"
        if transition(db, s.id, s.attempt, State.TIMED_OUT, reason, now=now):
            out.timed_out.append(s.id)
    db.commit()


def end_lost(
    db: Session,
    s: Submission,
    *,
    cause: Cause,
    detail: str | None = None,
    now: datetime | None = None,
    **values: object,
) -> bool | None:
    """End an attempt that died through no fault of the policy's (its worker lost or restarted,
    the cluster stopped it, the service was stopped): `error` (ours, no quota) and queued again
    as a new attempt: always after a stop, else the first time this submission loses one.
    `detail` says what happened instead of the cause's stock phrase; `values` are stored with
    the ended attempt (its log tail). True: queued again; False: left `error`; None: it had
    already moved on."""
    now = now or utcnow()
    earlier = cause in LOST_CAUSES and db.scalar(
        select(func.count())
        .select_from(Transition)
        .where(Transition.submission_id == s.id, Transition.cause.in_(LOST_CAUSES))
    )
    again = not earlier  # our fault once: run it again; twice: stop and say so
    what = detail or _WHAT[cause]
    reason = (
        f"{what}; queued again" if again else f"{what}; lost before, so not again: ask an admin"
    )
    if not transition(db, s.id, s.attempt, State.ERROR, reason, now=now, cause=cause, **values):
        return None
    db.refresh(s)
    if again:
        return new_attempt(
            db,
            s,
            _AGAIN.get(cause, f"{_WHAT[cause]}: running it again"),
            from_states=frozenset({State.ERROR}),
            now=now,
        )
    return False
