"""The internal API, ``/internal/v1``: what workers claim and report, and who may call it.

Driven through the worker's own client (`ServerAPI`, over an in-process transport) where the
worker's view is what matters, and through a plain test client where the HTTP answer itself
(a status, a body, an authentication failure) is the point.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from pydantic import SecretStr
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, joinedload, sessionmaker

from evaluator.plan import build_plan
from evaluator.results import Abort
from internal_api.schemas import (
    Assignment,
    AttemptRef,
    FinalReport,
    Progress,
    ReportOut,
    State,
)
from server.challenges.service import suite_of
from server.kit.settings import Settings
from server.models import Cause, EpisodeResultRow, Submission, TaskResultRow, Transition, utcnow
from server.submissions.service import cancel
from testkit.factories import (
    RecordingQueue,
    make_challenge,
    make_user,
    queue_submission,
    result_doc,
    token_for,
)
from testkit.workers import server_api, server_app, worker_settings
from worker.server_api import ServerAPI, WorkerRefused

ATTEMPT = "/internal/v1/submissions/{sid}/attempts/{attempt}"


@pytest.fixture
def app(
    settings: Settings, committed_sessions: sessionmaker[Session], work: RecordingQueue
) -> FastAPI:
    return server_app(settings, committed_sessions, work)


@pytest.fixture
def api(app: FastAPI, settings: Settings) -> Iterator[ServerAPI]:
    client = server_api(app, worker_settings(settings))
    yield client
    client.close()


@pytest.fixture
def http(app: FastAPI) -> Iterator[TestClient]:
    """The app over plain HTTP, without any credentials."""
    with TestClient(app, base_url="http://testserver") as client:
        yield client


def worker_auth(settings: Settings) -> dict[str, str]:
    return {"Authorization": f"Bearer {settings.secret('worker_token')}"}


def queue(
    sessions: sessionmaker[Session], per_user: dict[str, int], phase: str = "dev"
) -> list[int]:
    """Queued submissions, oldest first, of each user in turn."""
    with sessions() as db:
        challenge = make_challenge(db, quota_concurrent=100, quota_per_day=100)
        ids = []
        for name, n in per_user.items():
            user = make_user(db, name)
            ids += [queue_submission(db, user, challenge, phase).id for _ in range(n)]
        db.commit()
    return ids


def loaded(sessions: sessionmaker[Session], sid: int) -> Submission:
    with sessions() as db:
        s = db.get(
            Submission,
            sid,
            options=[joinedload(Submission.challenge), joinedload(Submission.user)],
        )
        assert s is not None
        return s


def claimed_and_running(api: ServerAPI, sid: int) -> None:
    handed = api.claim("w1")
    assert handed is not None
    assert (handed.submission_id, handed.attempt) == (sid, 1)
    assert api.running(sid, 1, reason="evaluating", deadline_s=600) == ReportOut(
        applied=True, state=State.RUNNING
    )


def age(sessions: sessionmaker[Session], sid: int) -> None:
    """Time passes for the server: the worker last reported 4 minutes ago."""
    long_ago = utcnow() - timedelta(minutes=4)
    with sessions.begin() as db:
        db.execute(
            update(Submission)
            .where(Submission.id == sid)
            .values(heartbeat_at=long_ago, updated_at=long_ago)
        )


# Claims ----------------------------------------------------------------------------------------


def test_a_claim_hands_out_the_fairest_queued_submission_with_its_evaluation(
    committed_sessions: sessionmaker[Session], settings: Settings, api: ServerAPI
) -> None:
    alice1, alice2, bob = queue(committed_sessions, {"alice": 2, "bob": 1})
    handed = api.claim("w1")
    assert handed is not None
    s = loaded(committed_sessions, alice1)
    suite = suite_of(s.challenge)
    secret = settings.secret("seed_secret").encode()
    assert handed == Assignment(
        submission_id=alice1,
        attempt=1,
        image=s.pinned_image,
        plan=build_plan(suite, "dev", secret=secret),
        suite_yaml=s.challenge.suite_yaml,
        shards=1,
    )
    assert (s.state, s.worker) == (State.LAUNCHING, "w1")  # who claimed it is recorded
    claims = [api.claim("w2") for _ in range(2)]
    assert [c.submission_id for c in claims if c is not None] == [bob, alice2]  # bob first
    assert api.claim("w2") is None
    assert loaded(committed_sessions, bob).worker == "w2"


def test_nothing_queued_is_204(http: TestClient, settings: Settings, api: ServerAPI) -> None:
    r = http.post("/internal/v1/claims", json={"worker": "w1"}, headers=worker_auth(settings))
    assert (r.status_code, r.content) == (204, b"")
    assert api.claim("w1") is None


def test_a_worker_name_must_be_printable_without_spaces(
    http: TestClient, settings: Settings
) -> None:
    r = http.post("/internal/v1/claims", json={"worker": "a b"}, headers=worker_auth(settings))
    assert r.status_code == 422


def test_a_secret_phase_is_handed_out_as_concrete_seeds_never_as_the_secret(
    committed_sessions: sessionmaker[Session], http: TestClient, settings: Settings
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1}, phase="test")
    r = http.post("/internal/v1/claims", json={"worker": "w1"}, headers=worker_auth(settings))
    assert r.status_code == 200
    handed = Assignment.model_validate(r.json())
    suite = suite_of(loaded(committed_sessions, sid).challenge)
    secret = settings.secret("seed_secret")
    assert handed.plan.phase == "test"
    assert all(run.seeds for run in handed.plan.runs)
    assert handed.plan == build_plan(suite, "test", secret=secret.encode())
    assert handed.plan != build_plan(suite, "test", secret=b"another secret" * 3)
    assert len(secret) >= 32
    assert secret not in r.text


# Reports ---------------------------------------------------------------------------------------


def test_running_sets_the_deadline(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    assert api.claim("w1") is not None
    before = utcnow()
    out = api.running(sid, 1, reason="evaluating", deadline_s=600)
    after = utcnow()
    assert out == ReportOut(applied=True, state=State.RUNNING)
    s = loaded(committed_sessions, sid)
    assert (s.state, s.reason) == (State.RUNNING, "evaluating")
    assert s.deadline_at is not None
    assert before + timedelta(seconds=600) <= s.deadline_at <= after + timedelta(seconds=600)


def test_a_heartbeat_keeps_the_last_progress(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    progress: Progress = {"done": 1, "total": 4, "task": "PickCube-v1"}
    assert api.progress(sid, 1, progress) == ReportOut(applied=True, state=State.RUNNING)
    age(committed_sessions, sid)
    assert api.silent() == [AttemptRef(submission_id=sid, attempt=1)]
    assert api.progress(sid, 1, None) == ReportOut(applied=True, state=State.RUNNING)
    assert api.silent() == []  # the heartbeat counted
    assert loaded(committed_sessions, sid).progress == progress  # and erased nothing


def test_reports_on_a_cancelled_attempt_no_longer_apply(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    assert api.progress(sid, 1, {"done": 1, "total": 4}).applied
    with committed_sessions.begin() as db:
        s = db.get(Submission, sid, options=[joinedload(Submission.user)])
        assert s is not None
        cancel(db, s.user, s)
    cancelled = ReportOut(applied=False, state=State.CANCELLED)
    assert api.progress(sid, 1, {"done": 2, "total": 4}) == cancelled
    assert api.running(sid, 1, reason="again", deadline_s=600) == cancelled
    assert loaded(committed_sessions, sid).progress == {"done": 1, "total": 4}
    assert api.final(sid, 1, FinalReport(state=State.FAILED, reason="late")) == State.CANCELLED
    assert loaded(committed_sessions, sid).state == State.CANCELLED


def test_what_ran_of_a_cancelled_attempt_is_kept_once_and_its_end_unchanged(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    """The worker sees a cancel at its next report and stops; what ran until then comes
    after the end, in a final report of the state the server gave it."""
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    with committed_sessions.begin() as db:
        s = db.get(Submission, sid, options=[joinedload(Submission.user)])
        assert s is not None
        cancel(db, s.user, s)
    ran = result_doc([True, False, True], planned=8)
    other = result_doc([True] * 8)
    assert api.final(sid, 1, FinalReport(state=State.FAILED, reason="x", result=other)) == (
        State.CANCELLED
    )
    assert loaded(committed_sessions, sid).result is None  # not the state it ended in
    for result in (ran, other):  # kept once: a later report replaces nothing
        report = FinalReport(state=State.CANCELLED, reason="what ran", result=result)
        assert api.final(sid, 1, report) == State.CANCELLED
    s = loaded(committed_sessions, sid)
    assert (s.state, s.reason, s.score) == (State.CANCELLED, "cancelled by its owner", None)
    assert s.result is not None
    assert s.result["conditions"][0]["tasks"][0]["successes"] == 2
    with committed_sessions() as db:
        rows = db.scalars(select(TaskResultRow).where(TaskResultRow.submission_id == sid)).all()
        assert [(r.episodes, r.episodes_ran, r.successes) for r in rows] == [(8, 3, 2)]
        episodes = db.scalars(
            select(EpisodeResultRow).where(EpisodeResultRow.task_result_id == rows[0].id)
        ).all()
        assert sorted(e.index for e in episodes) == [0, 1, 2]


def test_a_final_report_is_idempotent_and_the_first_final_state_wins(
    committed_sessions: sessionmaker[Session],
    http: TestClient,
    settings: Settings,
    api: ServerAPI,
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    url = ATTEMPT.format(sid=sid, attempt=1) + "/final"
    report = FinalReport(
        state=State.SUCCEEDED, reason="score 0.500", result=result_doc([True, False])
    ).model_dump(mode="json")
    auth = worker_auth(settings)
    for _ in range(2):  # a repeat (a retry after a lost answer) is applied, and changes nothing
        r = http.post(url, json=report, headers=auth)
        assert (r.status_code, r.json()) == (200, {"applied": True, "state": "succeeded"})
    other = {"state": "failed", "reason": "the policy crashed"}
    r = http.post(url, json=other, headers=auth)
    assert (r.status_code, r.json()) == (200, {"applied": False, "state": "succeeded"})
    s = loaded(committed_sessions, sid)
    assert (s.state, s.reason, s.score) == (State.SUCCEEDED, "score 0.500", 0.5)
    with committed_sessions() as db:
        ends = db.scalar(
            select(func.count())
            .select_from(Transition)
            .where(Transition.submission_id == sid, Transition.to_state == State.SUCCEEDED)
        )
        rows = db.scalar(
            select(func.count())
            .select_from(TaskResultRow)
            .where(TaskResultRow.submission_id == sid)
        )
    assert (ends, rows) == (1, 1)


def test_a_final_state_must_be_final(http: TestClient, settings: Settings) -> None:
    url = ATTEMPT.format(sid=1, attempt=1) + "/final"
    r = http.post(url, json={"state": "running", "reason": "x"}, headers=worker_auth(settings))
    assert r.status_code == 422


def test_an_error_the_cluster_caused_runs_again_once_and_is_sent_to_a_worker(
    committed_sessions: sessionmaker[Session],
    http: TestClient,
    settings: Settings,
    api: ServerAPI,
    work: RecordingQueue,
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    evicted = "the cluster stopped the evaluation: pod eval-1-1-0 was evicted"
    for attempt in (1, 2):
        handed = api.claim("w1")
        assert handed is not None
        assert handed.attempt == attempt
        api.running(sid, attempt, reason="evaluating", deadline_s=600)
        report = FinalReport(state=State.ERROR, reason=evicted, cause="cluster")
        state = api.final(sid, attempt, report)
        assert state == (State.QUEUED if attempt == 1 else State.ERROR)
    assert work.sent[-1] == (sid, 2)  # the re-run was sent after the commit
    s = loaded(committed_sessions, sid)
    assert (s.state, s.attempt) == (State.ERROR, 2)  # twice is not chance: stop and say so
    assert s.reason == f"{evicted}; lost before, so not again: ask an admin"
    with committed_sessions() as db:
        ends = db.execute(
            select(Transition.attempt, Transition.reason, Transition.cause)
            .where(Transition.submission_id == sid, Transition.to_state == State.ERROR)
            .order_by(Transition.attempt)
        ).all()
    assert [tuple(e) for e in ends] == [
        (1, f"{evicted}; queued again", Cause.CLUSTER),
        (2, s.reason, Cause.CLUSTER),
    ]
    r = http.post(
        ATTEMPT.format(sid=sid, attempt=2) + "/final",
        json={"state": "failed", "reason": "x", "cause": "cluster"},
        headers=worker_auth(settings),
    )
    assert r.status_code == 422  # a cause goes with `error` only


def test_what_a_policy_writes_is_stored_even_with_characters_a_database_refuses(
    committed_sessions: sessionmaker[Session], api: ServerAPI, http: TestClient, settings: Settings
) -> None:
    """A policy's log, its crash reason and progress may hold NUL, which Postgres cannot
    store: it is kept with U+FFFD in its place, never a 500; other control characters (a
    colour code) stay. A lone surrogate is not text at all: refused."""
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    assert api.progress(sid, 1, {"done": 0, "total": 1, "task": "Pick\x00Cube"}).applied
    abort = Abort(kind="policy_crashed", reason="died\x00 here", log_tail="out\x00put\x1b[0m")
    result = result_doc([False]).model_copy(update={"status": "aborted", "abort": abort})
    report = FinalReport(
        state=State.FAILED, reason="died\x00 here", result=result, log_tail="out\x00put"
    )
    body = report.model_dump_json()
    url = ATTEMPT.format(sid=sid, attempt=1) + "/final"
    headers = worker_auth(settings) | {"content-type": "application/json"}
    surrogate = body.replace("out\\u0000put", "out\\ud800put")
    assert http.post(url, content=surrogate, headers=headers).status_code == 422  # not UTF-8
    r = http.post(url, content=body, headers=headers)
    assert (r.status_code, r.json()) == (200, {"applied": True, "state": "failed"})
    s = loaded(committed_sessions, sid)
    assert (s.reason, s.log_tail) == ("died\ufffd here", "out\ufffdput")
    assert s.result is not None
    assert s.result["abort"]["log_tail"] == "out\ufffdput\x1b[0m"


def test_a_report_about_a_stale_attempt_is_refused(
    committed_sessions: sessionmaker[Session],
    http: TestClient,
    settings: Settings,
    api: ServerAPI,
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    assert api.restarted("w1") == [sid]  # attempt 1 died with w1; attempt 2 is queued
    base = ATTEMPT.format(sid=sid, attempt=1)
    auth = worker_auth(settings)
    bodies = {
        "running": {"reason": "late", "deadline_s": 60},
        "progress": {"progress": {"done": 2}},
        "final": {"state": "failed", "reason": "late"},
    }
    for kind, body in bodies.items():
        assert http.post(f"{base}/{kind}", json=body, headers=auth).status_code == 409, kind
    assert http.get(base, headers=auth).status_code == 409
    # The worker's client drops such reports: nothing to retry, nothing kept in its spool.
    assert api.running(sid, 1, reason="late", deadline_s=60) is None
    assert api.final(sid, 1, FinalReport(state=State.FAILED, reason="late")) is None
    assert list(api.spool) == []
    assert api.assignment(sid, 1) is None
    s = loaded(committed_sessions, sid)
    assert (s.state, s.attempt) == (State.QUEUED, 2)  # the re-run is untouched
    assert (
        http.post(
            ATTEMPT.format(sid=999999, attempt=1) + "/final", json=bodies["final"], headers=auth
        ).status_code
        == 404
    )


def test_a_new_watcher_gets_the_running_attempts_evaluation_again(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    handed = api.claim("w1")
    assert handed is not None
    assert api.running(sid, 1, reason="evaluating", deadline_s=600) is not None
    assert api.assignment(sid, 1) == handed
    assert api.final(sid, 1, FinalReport(state=State.ERROR, reason="ours")) == State.ERROR
    assert api.assignment(sid, 1) is None  # ended: nothing to watch


# Reconciling and restarts ----------------------------------------------------------------------


def test_a_pass_through_the_api_ends_a_silent_attempt(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    (sid,) = queue(committed_sessions, {"alice": 1})
    claimed_and_running(api, sid)
    assert api.reconcile().lost == []
    age(committed_sessions, sid)
    out = api.reconcile()
    assert (out.lost, out.requeued) == ([sid], [sid])
    assert out.active == [AttemptRef(submission_id=sid, attempt=2)]
    assert api.silent() == []


def test_a_restarted_worker_ends_only_its_own_attempts_and_they_run_again_once(
    committed_sessions: sessionmaker[Session], api: ServerAPI
) -> None:
    launching, running, other, waiting = queue(
        committed_sessions, {"alice": 1, "bob": 1, "carol": 1, "dave": 1}
    )
    assert api.claim("w1") is not None
    assert api.claim("w1") is not None
    assert api.running(running, 1, reason="evaluating", deadline_s=600) is not None
    handed = api.claim("w2")
    assert handed is not None
    assert handed.submission_id == other

    assert sorted(api.restarted("w1")) == sorted([launching, running])
    for sid in (launching, running):
        s = loaded(committed_sessions, sid)
        assert (s.state, s.attempt) == (State.QUEUED, 2)
    assert loaded(committed_sessions, other).state == State.LAUNCHING  # w2's
    assert loaded(committed_sessions, waiting).state == State.QUEUED
    with committed_sessions() as db:
        causes = db.execute(
            select(Transition.submission_id, Transition.to_state, Transition.cause).where(
                Transition.cause.is_not(None)
            )
        ).all()
    assert sorted(causes) == sorted(
        [(sid, State.ERROR, Cause.WORKER_RESTARTED) for sid in (launching, running)]
    )
    assert api.restarted("w1") == []  # nothing of w1's in flight

    # Claimed again by the restarted w1, and lost with it again: left `error` this time.
    again = [api.claim("w1") for _ in range(3)]
    assert {(a.submission_id, a.attempt) for a in again if a is not None} == {
        (waiting, 1),
        (launching, 2),
        (running, 2),
    }
    assert sorted(api.restarted("w1")) == sorted([waiting, launching, running])
    for sid in (launching, running):
        s = loaded(committed_sessions, sid)
        assert (s.state, s.attempt) == (State.ERROR, 2)
    assert loaded(committed_sessions, waiting).attempt == 2  # its first loss: queued again


# Who may call it -------------------------------------------------------------------------------

ROUTES = [
    ("POST", "/internal/v1/claims", {"worker": "w1"}),
    ("GET", ATTEMPT.format(sid=1, attempt=1), None),
    ("POST", ATTEMPT.format(sid=1, attempt=1) + "/running", {"reason": "x", "deadline_s": 1}),
    ("POST", ATTEMPT.format(sid=1, attempt=1) + "/progress", {"progress": None}),
    ("POST", ATTEMPT.format(sid=1, attempt=1) + "/final", {"state": "error", "reason": "x"}),
    ("GET", "/internal/v1/attempts/silent", None),
    ("POST", "/internal/v1/reconcile", None),
    ("POST", "/internal/v1/workers/w1/restarted", None),
]


def test_every_internal_route_needs_the_worker_token(
    committed_sessions: sessionmaker[Session], http: TestClient, settings: Settings
) -> None:
    with committed_sessions() as db:
        make_user(db, "alice")
    user_token = token_for(http, "alice")
    refused: list[dict[str, str]] = [
        {},
        user_token,  # a participant's API token opens the public API only
        {"Authorization": "Bearer " + "w" * 43},
        {"Authorization": f"Basic {settings.secret('worker_token')}"},
        {"Authorization": settings.secret("worker_token")},
    ]
    for method, url, body in ROUTES:
        for headers in refused:
            r = http.request(method, url, json=body, headers=headers)
            assert r.status_code == 401, (method, url, headers)
    r = http.post("/internal/v1/claims", json={"worker": "w1"}, headers=worker_auth(settings))
    assert r.status_code == 204


def test_a_worker_with_a_wrong_token_is_told_so(app: FastAPI, settings: Settings) -> None:
    wrong = worker_settings(settings, worker_token=SecretStr("x" * 40))
    client = server_api(app, wrong)
    try:
        with pytest.raises(WorkerRefused):
            client.claim("w1")
    finally:
        client.close()


def test_during_a_rotation_the_next_worker_token_is_accepted_too(
    settings: Settings, committed_sessions: sessionmaker[Session]
) -> None:
    upcoming = "n" * 40
    rotating = settings.model_copy(update={"worker_token_next": SecretStr(upcoming)})
    with TestClient(server_app(rotating, committed_sessions)) as http:
        for token in (settings.secret("worker_token"), upcoming):
            r = http.post(
                "/internal/v1/claims",
                json={"worker": "w1"},
                headers={"Authorization": f"Bearer {token}"},
            )
            assert r.status_code == 204
        r = http.post(
            "/internal/v1/claims",
            json={"worker": "w1"},
            headers={"Authorization": "Bearer " + "m" * 40},
        )
        assert r.status_code == 401


def test_the_internal_api_is_not_in_the_public_schema(http: TestClient) -> None:
    schema = http.get("/openapi.json")
    assert schema.status_code == 200
    assert "/api/v1/" in schema.text
    assert "/internal" not in schema.text
