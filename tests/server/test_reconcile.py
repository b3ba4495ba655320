"""The server's side of reconciling: it times out what is overdue, ends what was lost (and runs
it again once), wakes the queue, sends what the outbox holds, and says what is still active.

Lost attempts are recognised by their transition's typed cause, never by the reason's text; a
worker that restarted ends, at once, the attempts that died with it (`end_restarted`).
"""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import AttemptRef
from server.models import Cause, Outbox, State, Submission, Transition, utcnow
from server.submissions.reconcile import reconcile, silent
from server.submissions.reports import report_final, report_state
from server.submissions.states import new_attempt
from server.submissions.work import claim_next, end_restarted
from testkit.factories import RecordingQueue, make_challenge, make_user, queue_submission

LATER = timedelta(minutes=4)  # past the heartbeat timeout (3 minutes)


def _submission(db: Session, name: str = "alice") -> Submission:
    (s,) = _submissions(db, {name: 1})
    return s


def _submissions(db: Session, per_user: dict[str, int]) -> list[Submission]:
    """Queued submissions, oldest first, of each user in turn."""
    challenge = make_challenge(db, quota_concurrent=100, quota_per_day=100)
    queued = []
    for name, n in per_user.items():
        user = make_user(db, name)
        queued += [queue_submission(db, user, challenge) for _ in range(n)]
    db.commit()
    return queued


def _running(db: Session, s: Submission, **values: object) -> None:
    assert report_state(db, s.id, s.attempt, State.LAUNCHING, "go")
    assert report_state(db, s.id, s.attempt, State.RUNNING, "go")
    for key, value in values.items():
        setattr(s, key, value)
    db.commit()


def _history(db: Session, s: Submission) -> list[tuple[State, Cause | None]]:
    rows = db.execute(
        select(Transition.to_state, Transition.cause)
        .where(Transition.submission_id == s.id)
        .order_by(Transition.id)
    ).all()
    return [(state, cause) for state, cause in rows]


def test_overdue_runs_time_out(sessions: sessionmaker[Session], db: Session) -> None:
    s = _submission(db)
    _running(db, s, deadline_at=utcnow() + timedelta(minutes=5))
    assert reconcile(sessions, RecordingQueue()).timed_out == []
    out = reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=6))
    assert out.timed_out == [s.id]
    assert out.lost == []  # timed out: the policy's budget, not a lost worker
    db.refresh(s)
    assert s.state == State.TIMED_OUT
    assert "time budget" in s.reason


def test_a_lost_worker_is_our_error_and_runs_again_once(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    _running(db, s)
    later = utcnow() + LATER
    work = RecordingQueue()
    out = reconcile(sessions, work, now=later)
    assert out.lost == [s.id]
    assert out.requeued == [s.id]
    db.refresh(s)
    assert (s.state, s.attempt) == (State.QUEUED, 2)
    assert (s.id, 2) in work.sent  # the new attempt's outbox row was sent by the pass
    _running(db, s)
    out = reconcile(sessions, work, now=later + LATER)
    assert out.lost == [s.id]
    assert out.requeued == []
    db.refresh(s)
    assert (s.state, s.attempt) == (State.ERROR, 2)
    assert "again" in s.reason
    assert _history(db, s) == [
        (State.QUEUED, None),
        (State.LAUNCHING, None),
        (State.RUNNING, None),
        (State.ERROR, Cause.WORKER_LOST),
        (State.QUEUED, None),
        (State.LAUNCHING, None),
        (State.RUNNING, None),
        (State.ERROR, Cause.WORKER_LOST),
    ]


def test_an_earlier_loss_is_known_by_its_cause_not_its_reason(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    _running(db, s)
    # An error whose text reads like a loss, but is no loss (no cause): say, a worker's own.
    lookalike = "the worker evaluating it stopped responding; queued again"
    assert report_final(db, s.id, 1, State.ERROR, lookalike)
    db.commit()
    db.refresh(s)
    assert new_attempt(db, s, "re-run by an admin")
    db.commit()
    _running(db, s)
    out = reconcile(sessions, RecordingQueue(), now=utcnow() + LATER)
    assert (out.lost, out.requeued) == ([s.id], [s.id])  # the first real loss: again, once
    db.refresh(s)
    assert (s.state, s.attempt) == (State.QUEUED, 3)


def test_a_restart_counts_as_the_one_loss_that_is_run_again(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    assert claim_next(db, worker="w1", max_running_per_user=10) == (s.id, 1)
    assert end_restarted(db, worker="w1") == [s.id]
    db.commit()
    db.refresh(s)
    assert (s.state, s.attempt) == (State.QUEUED, 2)
    _running(db, s)
    out = reconcile(sessions, RecordingQueue(), now=utcnow() + LATER)
    assert (out.lost, out.requeued) == ([s.id], [])
    db.refresh(s)
    assert (s.state, s.attempt) == (State.ERROR, 2)
    causes = [cause for _, cause in _history(db, s) if cause is not None]
    assert causes == [Cause.WORKER_RESTARTED, Cause.WORKER_LOST]


def test_heartbeats_keep_a_run_alive(sessions: sessionmaker[Session], db: Session) -> None:
    s = _submission(db)
    _running(db, s, heartbeat_at=utcnow() + timedelta(minutes=3))
    out = reconcile(sessions, RecordingQueue(), now=utcnow() + LATER)
    assert out.lost == []
    assert out.active == [AttemptRef(submission_id=s.id, attempt=1)]


def test_a_launch_that_never_starts_is_lost(sessions: sessionmaker[Session], db: Session) -> None:
    s = _submission(db)
    assert report_state(db, s.id, 1, State.LAUNCHING, "pulling")
    db.commit()
    assert reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=5)).lost == []
    out = reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=16))
    assert out.lost == [s.id]
    db.refresh(s)
    assert (s.state, s.attempt) == (State.QUEUED, 2)


def test_waiting_submissions_get_wake_ups_and_the_outbox_is_sent(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    work = RecordingQueue()
    assert reconcile(sessions, work).woken == 0  # just queued: its own message is enough
    assert work.sent == [(s.id, 1)]  # the unsent outbox row, sent once
    out = reconcile(sessions, work, now=utcnow() + timedelta(minutes=3))
    assert out.woken == 1
    assert work.sent == [(s.id, 1), (0, 0)]  # then a wake-up, not the row again
    assert out.active == [AttemptRef(submission_id=s.id, attempt=1)]


def test_a_broker_that_refuses_messages_does_not_fail_the_pass(
    sessions: sessionmaker[Session], db: Session
) -> None:
    class Down:
        def enqueue(self, submission_id: int, attempt: int) -> None:
            raise ConnectionError("the broker is down")

    waiting, lost = _submissions(db, {"alice": 1, "bob": 1})
    _running(db, lost)
    out = reconcile(sessions, Down(), now=utcnow() + LATER)
    assert (out.lost, out.requeued, out.woken) == ([lost.id], [lost.id], 0)
    assert db.scalars(select(Outbox.attempt).where(Outbox.sent_at.is_(None))).all() != []
    work = RecordingQueue()  # the broker is back: nothing was lost meanwhile
    reconcile(sessions, work)
    assert sorted(work.sent) == sorted([(waiting.id, 1), (lost.id, 1), (lost.id, 2)])


def test_only_running_attempts_past_the_heartbeat_timeout_are_silent(db: Session) -> None:
    running, fresh, launching = _submissions(db, {"alice": 1, "bob": 1, "carol": 1})
    _running(db, running)
    _running(db, fresh, heartbeat_at=utcnow() + timedelta(minutes=3))
    assert report_state(db, launching.id, 1, State.LAUNCHING, "pulling")
    db.commit()
    assert silent(db) == []
    later = utcnow() + LATER
    assert silent(db, now=later) == [AttemptRef(submission_id=running.id, attempt=1)]


def test_a_restarted_worker_ends_only_its_own_attempts_in_flight(db: Session) -> None:
    launching, running, finished, w2_launching, w2_running, waiting = _submissions(db, {"alice": 6})
    for s in (launching, running, finished):
        assert claim_next(db, worker="w1", max_running_per_user=10) == (s.id, 1)
    for s in (w2_launching, w2_running):
        assert claim_next(db, worker="w2", max_running_per_user=10) == (s.id, 1)
    for s in (running, finished, w2_running):
        assert report_state(db, s.id, 1, State.RUNNING, "go")
    assert report_final(db, finished.id, 1, State.FAILED, "the policy crashed")
    db.commit()

    assert sorted(end_restarted(db, worker="w1")) == sorted([launching.id, running.id])
    db.commit()
    for s in (launching, running):
        db.refresh(s)
        assert (s.state, s.attempt) == (State.QUEUED, 2)  # ours, the first time: run again
        assert s.reason == "the worker evaluating it restarted: running it again"
        assert (State.ERROR, Cause.WORKER_RESTARTED) in _history(db, s)
    untouched = {
        finished: State.FAILED,
        w2_launching: State.LAUNCHING,
        w2_running: State.RUNNING,
        waiting: State.QUEUED,
    }
    for s, state in untouched.items():
        db.refresh(s)
        assert (s.state, s.attempt) == (state, 1)
    assert end_restarted(db, worker="w1") == []  # nothing of w1's is in flight any more

    # The second time the same submission dies with its worker, it stays `error`.
    again = {claim_next(db, worker="w1", max_running_per_user=10) for _ in range(3)}
    assert {(launching.id, 2), (running.id, 2)} <= again
    assert sorted(end_restarted(db, worker="w1")) == sorted([launching.id, running.id, waiting.id])
    db.commit()
    for s in (launching, running):
        db.refresh(s)
        assert (s.state, s.attempt) == (State.ERROR, 2)
        assert "again" in s.reason
    db.refresh(waiting)
    assert (waiting.state, waiting.attempt) == (State.QUEUED, 2)
