"""The reconciler: compares what the database says with what is really going on, and decides.

Run periodically (Celery beat, or the embedded server's sweeper). Each pass:
- times out runs past their deadline (`timed_out`; the running worker sees it and stops);
- ends runs whose worker stopped reporting (`error`), and queues them once more as a new
  attempt, since that was our fault; a second loss of the same submission stays `error`;
- sends what the outbox still holds, and wakes workers for queued submissions that have
  waited too long (a lost message);
- removes containers and Jobs that belong to no active attempt (a worker that crashed).
Watch events or messages are hints; this pass is what guarantees every submission ends.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from server.models import ACTIVE_STATES, State, Submission, Transition, utcnow
from server.submissions.outbox import Dispatcher, WorkQueue
from server.submissions.states import new_attempt, transition

log = logging.getLogger(__name__)

WORKER_LOST = "the worker evaluating it stopped responding"
Cleaner = Callable[[set[tuple[int, int]]], list[str]]
"""Removes runtime resources (containers, Jobs) of attempts not in the given active set."""
Resumer = Callable[[int, int], bool]
"""For a running attempt whose watcher went silent: True when its evaluation still exists
elsewhere (a Kubernetes Job) and a new watcher has been sent for it; raises when it cannot
tell (the attempt is then left for the next pass)."""


@dataclass(frozen=True)
class Timeouts:
    heartbeat: timedelta = timedelta(minutes=3)
    """A running attempt whose worker has not reported for this long is lost."""
    launch: timedelta = timedelta(minutes=15)
    """A launching attempt (pulling an image) that has not started running by then is lost."""
    requeue: timedelta = timedelta(minutes=2)
    """A queued submission untouched this long gets a fresh wake-up message."""


@dataclass
class Report:
    timed_out: list[int] = field(default_factory=list)
    lost: list[int] = field(default_factory=list)
    requeued: list[int] = field(default_factory=list)
    resumed: list[int] = field(default_factory=list)
    woken: int = 0
    removed: list[str] = field(default_factory=list)


def reconcile(
    sessions: sessionmaker[Session],
    work: WorkQueue,
    *,
    cleaners: Sequence[Cleaner] = (),
    resume: Resumer | None = None,
    timeouts: Timeouts = Timeouts(),
    now: datetime | None = None,
) -> Report:
    now = now or utcnow()
    report = Report()
    with sessions() as db:
        for s in db.scalars(
            select(Submission).where(
                Submission.state.in_([State.LAUNCHING, State.RUNNING]),
                Submission.deadline_at.is_not(None),
                Submission.deadline_at < now,
            )
        ):
            if transition(
                db,
                s.id,
                s.attempt,
                State.TIMED_OUT,
                "the evaluation exceeded its time budget",
                now=now,
            ):
                report.timed_out.append(s.id)
        db.commit()

        stale_running = (Submission.state == State.RUNNING) & (
            func.coalesce(Submission.heartbeat_at, Submission.updated_at) < now - timeouts.heartbeat
        )
        stale_launch = (Submission.state == State.LAUNCHING) & (
            Submission.updated_at < now - timeouts.launch
        )
        for s in db.scalars(select(Submission).where(stale_running | stale_launch)):
            if s.state == State.RUNNING and resume is not None:
                resumed = _resume(db, s, resume, now)
                if resumed is None:
                    continue  # cannot tell now: the next pass looks again
                if resumed:
                    report.resumed.append(s.id)
                    continue
            _lost(db, s, now, report)
            db.commit()

        waiting = db.scalar(
            select(func.count())
            .select_from(Submission)
            .where(Submission.state == State.QUEUED, Submission.updated_at < now - timeouts.requeue)
        )
        active = {
            (sid, attempt)
            for sid, attempt in db.execute(
                select(Submission.id, Submission.attempt).where(Submission.state.in_(ACTIVE_STATES))
            )
        }
    Dispatcher(sessions, work).dispatch()  # outbox rows no server sent (e.g. re-queued above)
    for _ in range(waiting or 0):
        try:
            work.enqueue(0, 0)  # a wake-up: the worker claims the fairest queued submission
            report.woken += 1
        except Exception:
            log.exception("could not send a wake-up; the next pass will try again")
            break
    for clean in cleaners:
        try:
            report.removed += clean(active)
        except Exception:
            log.exception("cleaning leftovers failed; the next pass will try again")
    if report.timed_out or report.lost or report.removed or report.resumed:
        log.info("reconciled: %s", report)
    return report


def _resume(db: Session, s: Submission, resume: Resumer, now: datetime) -> bool | None:
    """Hand a silent attempt to a new watcher when its evaluation is still there; None when
    that cannot be told now."""
    try:
        if not resume(s.id, s.attempt):
            return False
    except Exception:
        log.exception("cannot tell whether submission %s still runs; next pass", s.id)
        return None
    db.execute(  # the new watcher's first look will follow; until then, not silent
        update(Submission)
        .where(Submission.id == s.id, Submission.attempt == s.attempt)
        .values(heartbeat_at=now)
    )
    db.commit()
    return True


def _lost(db: Session, s: Submission, now: datetime, report: Report) -> None:
    earlier = db.scalar(
        select(func.count())
        .select_from(Transition)
        .where(
            Transition.submission_id == s.id,
            Transition.to_state == State.ERROR,
            Transition.reason.like(f"{WORKER_LOST}%"),
        )
    )
    again = not earlier  # our fault once: run it again; twice: stop and say so
    reason = f"{WORKER_LOST}; queued again" if again else f"{WORKER_LOST} again; ask an admin"
    if not transition(db, s.id, s.attempt, State.ERROR, reason, now=now):
        return
    report.lost.append(s.id)
    db.refresh(s)
    if again and new_attempt(
        db, s, f"{WORKER_LOST}: running it again", from_states=frozenset({State.ERROR}), now=now
    ):
        report.requeued.append(s.id)
