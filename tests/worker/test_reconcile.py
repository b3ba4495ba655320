"""The reconciler ends what is overdue or lost, re-queues our failures once, wakes the queue
and removes leftovers."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.models import State, Submission, Transition, utcnow
from server.submissions.reports import report_state
from tests.factories import RecordingQueue, make_challenge, make_user, queue_submission
from worker.reconcile import reconcile


def _submission(db: Session, name: str = "alice") -> Submission:
    challenge = make_challenge(db, quota_concurrent=100, quota_per_day=100)
    s = queue_submission(db, make_user(db, name), challenge)
    db.commit()
    return s


def _running(db: Session, s: Submission, **values: object) -> None:
    assert report_state(db, s.id, s.attempt, State.LAUNCHING, "go")
    assert report_state(db, s.id, s.attempt, State.RUNNING, "go")
    for key, value in values.items():
        setattr(s, key, value)
    db.commit()


def test_overdue_runs_time_out(sessions: sessionmaker[Session], db: Session) -> None:
    s = _submission(db)
    _running(db, s, deadline_at=utcnow() + timedelta(minutes=5))
    assert reconcile(sessions, RecordingQueue()).timed_out == []
    report = reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=6))
    assert report.timed_out == [s.id]
    db.refresh(s)
    assert s.state == State.TIMED_OUT
    assert "time budget" in s.reason


def test_a_lost_worker_is_our_error_and_runs_again_once(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    _running(db, s)
    later = utcnow() + timedelta(minutes=4)
    work = RecordingQueue()
    report = reconcile(sessions, work, now=later)
    assert report.lost == [s.id]
    assert report.requeued == [s.id]
    db.refresh(s)
    assert (s.state, s.attempt) == (State.QUEUED, 2)
    _running(db, s)
    report = reconcile(sessions, work, now=later + timedelta(minutes=4))
    assert report.lost == [s.id]
    assert report.requeued == []
    db.refresh(s)
    assert (s.state, s.attempt) == (State.ERROR, 2)
    assert "again" in s.reason
    history = db.scalars(
        select(Transition.to_state).where(Transition.submission_id == s.id).order_by(Transition.id)
    ).all()
    assert history == [
        State.QUEUED,
        State.LAUNCHING,
        State.RUNNING,
        State.ERROR,
        State.QUEUED,
        State.LAUNCHING,
        State.RUNNING,
        State.ERROR,
    ]


def test_heartbeats_keep_a_run_alive(sessions: sessionmaker[Session], db: Session) -> None:
    s = _submission(db)
    _running(db, s, heartbeat_at=utcnow() + timedelta(minutes=3))
    assert reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=4)).lost == []


def test_a_launch_that_never_starts_is_lost(sessions: sessionmaker[Session], db: Session) -> None:
    s = _submission(db)
    assert report_state(db, s.id, 1, State.LAUNCHING, "pulling")
    db.commit()
    assert reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=5)).lost == []
    report = reconcile(sessions, RecordingQueue(), now=utcnow() + timedelta(minutes=16))
    assert report.lost == [s.id]


def test_waiting_submissions_get_wake_ups_and_leftovers_are_cleaned(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    seen: list[set[tuple[int, int]]] = []

    def cleaner(active: set[tuple[int, int]]) -> list[str]:
        seen.append(active)
        return ["eval-99-1"]

    work = RecordingQueue()
    report = reconcile(sessions, work, cleaners=[cleaner], now=utcnow() + timedelta(minutes=3))
    assert report.woken == 1
    assert work.sent == [(s.id, 1), (0, 0)]  # the unsent outbox row, then a wake-up
    assert seen == [{(s.id, 1)}]
    assert report.removed == ["eval-99-1"]


def test_a_resumer_that_cannot_tell_leaves_the_attempt_for_the_next_pass(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    _running(db, s)

    def cannot_tell(_sid: int, _attempt: int) -> bool:
        raise ConnectionError("the API server does not answer")

    later = utcnow() + timedelta(minutes=4)
    report = reconcile(sessions, RecordingQueue(), resume=cannot_tell, now=later)
    assert (report.lost, report.resumed) == ([], [])
    db.refresh(s)
    assert s.state == State.RUNNING


def test_a_resumed_attempt_is_not_silent_until_its_new_watcher_reports(
    sessions: sessionmaker[Session], db: Session
) -> None:
    s = _submission(db)
    _running(db, s)
    sent: list[int] = []

    def resume(sid: int, _attempt: int) -> bool:
        sent.append(sid)
        return True

    later = utcnow() + timedelta(minutes=4)
    assert reconcile(sessions, RecordingQueue(), resume=resume, now=later).resumed == [s.id]
    soon = later + timedelta(minutes=1)  # within the heartbeat timeout of the hand-over
    assert reconcile(sessions, RecordingQueue(), resume=resume, now=soon).resumed == []
    assert sent == [s.id]
