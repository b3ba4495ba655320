"""The worker's side of a reconciling pass, through the internal API: silent attempts whose
evaluation still runs elsewhere are handed to a new watcher (and kept alive), then the server
decides, then leftovers of attempts that are no longer active are removed.

The server's own decisions (time-outs, lost attempts, wake-ups) are tested in
tests/server/test_reconcile.py; here the server is real but time does not pass, so a silent
attempt is made by ageing its heartbeat in the database.
"""

from __future__ import annotations

from datetime import datetime, timedelta

import pytest
from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import AttemptRef, State
from server.models import Submission, utcnow
from testkit.factories import RecordingQueue, make_challenge, make_user, queue_submission
from worker.reconcile import reconcile_pass
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

Active = set[tuple[int, int]]


@pytest.fixture
def queued(committed_sessions: sessionmaker[Session]) -> list[int]:
    """Two queued submissions, alice's then bob's."""
    with committed_sessions() as db:
        challenge = make_challenge(db, quota_concurrent=100, quota_per_day=100)
        ids = [queue_submission(db, make_user(db, name), challenge).id for name in ("alice", "bob")]
        db.commit()
    return ids


def running(api: ServerAPI, wsettings: WorkerSettings, sid: int) -> None:
    """Claim `sid` (the fairest queued) and report it running, as a worker does."""
    handed = api.claim(wsettings.worker_name)
    assert handed is not None
    assert (handed.submission_id, handed.attempt) == (sid, 1)
    out = api.running(sid, 1, reason="evaluating", deadline_s=3600)
    assert out is not None
    assert out.applied
    assert api.progress(sid, 1, {"done": 1, "total": 4}).applied


def age(sessions: sessionmaker[Session], sid: int, minutes: float = 4) -> datetime:
    """Time passes for the server: the attempt's worker last reported `minutes` ago."""
    long_ago = utcnow() - timedelta(minutes=minutes)
    with sessions.begin() as db:
        db.execute(
            update(Submission)
            .where(Submission.id == sid)
            .values(heartbeat_at=long_ago, updated_at=long_ago)
        )
    return long_ago


def submission(sessions: sessionmaker[Session], sid: int) -> Submission:
    with sessions() as db:
        s = db.get(Submission, sid)
        assert s is not None
        return s


def test_cleaners_get_the_active_attempts_and_report_what_they_removed(
    api: ServerAPI,
    wsettings: WorkerSettings,
    queued: list[int],
    work: RecordingQueue,
) -> None:
    alice, bob = queued
    running(api, wsettings, alice)
    seen: list[Active] = []

    def cleaner(active: Active) -> list[str]:
        seen.append(active)
        return ["eval-99-1"]

    def broken(_active: Active) -> list[str]:
        raise ConnectionError("the container engine does not answer")

    report = reconcile_pass(api, cleaners=[broken, cleaner])
    assert seen == [{(alice, 1), (bob, 1)}]  # running and queued: both still active
    assert report.removed == ["eval-99-1"]  # a failing cleaner does not stop the others
    assert report.resumed == []
    assert sorted(report.server.active, key=lambda r: r.submission_id) == [
        AttemptRef(submission_id=alice, attempt=1),
        AttemptRef(submission_id=bob, attempt=1),
    ]
    assert sorted(work.sent) == [(alice, 1), (bob, 1)]  # the server's pass sent its outbox


def test_a_resumable_silent_attempt_gets_a_heartbeat_and_is_not_lost(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    queued: list[int],
) -> None:
    sid = queued[0]
    running(api, wsettings, sid)
    long_ago = age(committed_sessions, sid)
    sent: list[tuple[int, int]] = []

    def resume(submission_id: int, attempt: int) -> bool:
        sent.append((submission_id, attempt))
        return True

    report = reconcile_pass(api, resume=resume)
    assert (report.resumed, report.server.lost, sent) == ([sid], [], [(sid, 1)])
    s = submission(committed_sessions, sid)
    assert s.state == State.RUNNING
    assert s.heartbeat_at is not None
    assert s.heartbeat_at > long_ago
    assert s.progress == {"done": 1, "total": 4}  # a heartbeat only: the progress stays
    # Until the new watcher reports, the hand-over's heartbeat keeps it from being silent.
    assert reconcile_pass(api, resume=resume).resumed == []
    assert sent == [(sid, 1)]


def test_a_silent_attempt_that_no_longer_runs_anywhere_is_lost(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    queued: list[int],
) -> None:
    sid = queued[0]
    running(api, wsettings, sid)
    age(committed_sessions, sid)
    report = reconcile_pass(api, resume=lambda _sid, _attempt: False)
    assert (report.resumed, report.server.lost, report.server.requeued) == ([], [sid], [sid])
    s = submission(committed_sessions, sid)
    assert (s.state, s.attempt) == (State.QUEUED, 2)


def test_a_resumer_that_cannot_tell_leaves_the_attempt_for_the_next_pass(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    queued: list[int],
) -> None:
    sid = queued[0]
    running(api, wsettings, sid)
    age(committed_sessions, sid)
    asked: list[int] = []

    def cannot_tell(submission_id: int, _attempt: int) -> bool:
        asked.append(submission_id)
        raise ConnectionError("the API server does not answer")

    report = reconcile_pass(api, resume=cannot_tell)
    assert (report.resumed, report.server.lost) == ([], [])
    assert submission(committed_sessions, sid).state == State.RUNNING

    def gone(submission_id: int, _attempt: int) -> bool:
        asked.append(submission_id)
        return False

    age(committed_sessions, sid)  # still silent at a later pass: asked again, and now it can tell
    report = reconcile_pass(api, resume=gone)
    assert asked == [sid, sid]
    assert report.server.lost == [sid]


def test_a_services_workers_share_one_id_that_does_not_reveal_their_token() -> None:
    token = "t" * 40
    one, other = (WorkerSettings(worker_token=token, worker_name=n) for n in ("a", "b"))
    moved = WorkerSettings(worker_token=token, server_url="http://10.0.0.5:9000")
    assert one.service_id == other.service_id == moved.service_id
    assert WorkerSettings(worker_token="u" * 40).service_id != one.service_id
    assert token not in one.service_id
