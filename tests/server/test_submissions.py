"""Submissions: accept and pin, quotas, the state machine under races, ingestion, leaderboard,
and who may see what."""

from __future__ import annotations

import logging
import threading
from datetime import UTC, datetime, timedelta

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.models import Outbox, State, Submission, Transition
from server.submissions.outbox import Unattached
from server.submissions.reports import report_final, report_state
from server.submissions.states import transition
from testkit.factories import RecordingQueue, make_challenge, make_user, result_doc, token_for

API = "/api/v1"
IMAGE = "127.0.0.1:5000/team/policy:v1"


def finish(db: Session, submission_id: int, successes: list[bool]) -> None:
    assert report_state(db, submission_id, 1, State.LAUNCHING, "starting")
    assert report_state(db, submission_id, 1, State.RUNNING, "evaluating")
    assert report_final(db, submission_id, 1, State.SUCCEEDED, "done", result=result_doc(successes))
    db.commit()


@pytest.fixture
def setup(client: TestClient, db: Session) -> dict[str, dict[str, str]]:
    make_challenge(db, quota_per_day=3, quota_concurrent=2)
    for name in ("alice", "bob"):
        make_user(db, name)
    make_user(db, "judge", admin=True)
    return {name: token_for(client, name) for name in ("alice", "bob", "judge")}


def submit(client: TestClient, headers: dict[str, str], **body: object) -> dict[str, object]:
    payload: dict[str, object] = {"challenge": "server-tiny", "phase": "dev", "image": IMAGE}
    payload.update(body)
    r = client.post(f"{API}/submissions", json=payload, headers=headers)
    return {"status": r.status_code, **r.json()}


def test_submit_pins_queues_after_commit_and_records_history(
    client: TestClient, setup: dict[str, dict[str, str]], work: RecordingQueue, db: Session
) -> None:
    out = submit(client, setup["alice"], description="first try")
    assert out["status"] == 202, out
    assert out["state"] == "queued"
    assert str(out["pinned_image"]).startswith("127.0.0.1:5000/team/policy@sha256:")
    assert work.sent == [(out["id"], 1)]
    outbox = db.scalars(select(Outbox)).all()
    assert [(o.submission_id, o.sent_at is not None) for o in outbox] == [(out["id"], True)]
    detail = client.get(f"{API}/submissions/{out['id']}", headers=setup["alice"]).json()
    assert [t["to_state"] for t in detail["transitions"]] == ["queued"]


def test_unsent_work_is_sent_by_the_next_dispatch(
    client: TestClient, setup: dict[str, dict[str, str]], work: RecordingQueue
) -> None:
    class Down:
        def enqueue(self, submission_id: int, attempt: int) -> None:
            raise ConnectionError("broker down")

    dispatcher = client.app.state.services.dispatcher  # type: ignore[attr-defined]
    dispatcher._work = Down()
    out = submit(client, setup["alice"])
    assert out["status"] == 202  # accepted: it is in the database and the outbox
    assert work.sent == []
    dispatcher._work = work
    assert dispatcher.dispatch() == 1
    assert work.sent == [(out["id"], 1)]
    assert dispatcher.dispatch() == 0


def test_work_waits_quietly_in_the_outbox_until_a_worker_is_attached(
    client: TestClient,
    setup: dict[str, dict[str, str]],
    work: RecordingQueue,
    caplog: pytest.LogCaptureFixture,
) -> None:
    dispatcher = client.app.state.services.dispatcher  # type: ignore[attr-defined]
    dispatcher._work = Unattached()
    with caplog.at_level(logging.INFO, logger="server.submissions.outbox"):
        out = submit(client, setup["alice"])
        assert dispatcher.dispatch() == 0
    assert out["status"] == 202
    assert [r for r in caplog.records if r.levelno >= logging.INFO] == []  # no trace per submit
    dispatcher._work = work  # `manieval serve` attaches its worker
    assert dispatcher.dispatch() == 1
    assert work.sent == [(out["id"], 1)]


@pytest.mark.parametrize(
    ("image", "problem"),
    [
        ("Team/Policy", "lowercase"),
        ("policy:" + "x" * 200, "128"),
        ("pólicy:v1", "ASCII"),
        ("", ""),
        ("a b", ""),
    ],
)
def test_bad_image_references_are_422_on_the_field(
    client: TestClient, setup: dict[str, dict[str, str]], image: str, problem: str
) -> None:
    out = submit(client, setup["alice"], image=image)
    assert out["status"] == 422
    error = out["error"]
    assert isinstance(error, dict)
    assert "image" in error["fields"]
    assert problem in error["message"] or problem in error["fields"]["image"]


def test_unknown_challenge_and_phase(client: TestClient, setup: dict[str, dict[str, str]]) -> None:
    assert submit(client, setup["alice"], challenge="nope")["status"] == 404
    out = submit(client, setup["alice"], phase="final")
    assert out["status"] == 422
    assert "dev, test" in str(out["error"])


def test_closed_phase_refuses(
    client: TestClient, setup: dict[str, dict[str, str]], db: Session
) -> None:
    past = datetime.now(UTC) - timedelta(days=1)
    make_challenge(db, closes={"dev": past}, opens={"dev": past - timedelta(days=9)})
    out = submit(client, setup["alice"])
    assert out["status"] == 409
    assert "closed" in str(out["error"])


def test_quota_counts_only_what_the_participant_caused(
    client: TestClient, setup: dict[str, dict[str, str]], db: Session
) -> None:
    alice = setup["alice"]
    first = submit(client, alice)
    second = submit(client, alice)
    third = submit(client, alice)
    assert third["status"] == 429  # two queued: the concurrent limit
    assert "queued or running" in str(third["error"])
    # Our error and a cancel release their reservation.
    assert transition(db, int(first["id"]), 1, State.ERROR, "worker lost")  # type: ignore[call-overload]
    db.commit()
    assert client.post(f"{API}/submissions/{second['id']}/cancel", headers=alice).status_code == 200
    a = submit(client, alice)
    b = submit(client, alice)
    assert a["status"] == b["status"] == 202
    for s in (a, b):
        finish(db, int(s["id"]), [True, False])  # type: ignore[call-overload]
    c = submit(client, alice)
    assert c["status"] == 202
    finish(db, int(c["id"]), [False, False])  # type: ignore[call-overload]
    d = submit(client, alice)  # three counted today: succeeded, succeeded, succeeded
    assert d["status"] == 429
    error = d["error"]
    assert isinstance(error, dict)
    assert error["code"] == "quota_exceeded"
    assert "resets_at" in error
    assert submit(client, setup["bob"])["status"] == 202  # quotas are per user


def test_private_submissions_are_404_and_public_ones_refuse_their_logs_and_episodes(
    client: TestClient, setup: dict[str, dict[str, str]], db: Session
) -> None:
    alice, bob, root = setup["alice"], setup["bob"], setup["judge"]
    private = submit(client, alice, public=False)
    public = submit(client, alice)
    for s in (private, public):
        finish(db, int(s["id"]), [True, True])  # type: ignore[call-overload]
    pid, qid = private["id"], public["id"]
    assert client.get(f"{API}/submissions/{pid}", headers=bob).status_code == 404
    assert client.get(f"{API}/submissions/{pid}").status_code == 404
    assert client.get(f"{API}/submissions/{pid}", headers=alice).status_code == 200
    assert client.get(f"{API}/submissions/{pid}", headers=root).status_code == 200
    assert client.get(f"{API}/submissions/{qid}", headers=bob).status_code == 200
    for suffix in ("logs", "episodes"):
        for sid in (pid, qid):
            assert client.get(f"{API}/submissions/{sid}/{suffix}", headers=alice).status_code == 200
        for headers in (bob, {}):  # a stranger and a visitor
            assert (
                client.get(f"{API}/submissions/{pid}/{suffix}", headers=headers).status_code == 404
            )
            # The public one exists: "no submission" would be a lie, the part is what is refused.
            r = client.get(f"{API}/submissions/{qid}/{suffix}", headers=headers)
            assert r.status_code == 403
            assert r.json()["error"]["message"] == (
                f"submission {qid} is public, but its {suffix} are visible to its owner only"
            )
    assert client.post(f"{API}/submissions/{qid}/cancel", headers=bob).status_code == 404
    r = client.patch(f"{API}/submissions/{qid}", json={"public": False}, headers=bob)
    assert r.status_code == 404
    assert client.get(f"{API}/submissions", headers=bob).json()["total"] == 0
    r = client.patch(f"{API}/submissions/{qid}", json={"baseline": True}, headers=alice)
    assert r.status_code == 403
    assert client.post(f"{API}/submissions/{qid}/rerun", headers=alice).status_code == 403


def test_secret_phase_seeds_never_leave_the_server(
    client: TestClient, setup: dict[str, dict[str, str]], db: Session
) -> None:
    alice = setup["alice"]
    s = submit(client, alice, phase="test")
    assert report_state(db, int(s["id"]), 1, State.LAUNCHING, "x")  # type: ignore[call-overload]
    assert report_state(db, int(s["id"]), 1, State.RUNNING, "x")  # type: ignore[call-overload]
    assert report_final(
        db,
        int(s["id"]),
        1,
        State.SUCCEEDED,
        "done",  # type: ignore[call-overload]
        result=result_doc([True], phase="test"),
    )
    db.commit()
    episodes = client.get(f"{API}/submissions/{s['id']}/episodes", headers=alice).json()
    assert episodes["items"]
    assert all(e["seed"] is None for e in episodes["items"])
    detail = client.get(f"{API}/submissions/{s['id']}", headers=alice).text
    assert "1000" not in detail
    challenge = client.get(f"{API}/challenges/server-tiny").json()
    commitments = {p["name"]: p["seed_commitment"] for p in challenge["phases"]}
    assert len(commitments["test"]) == 64


def test_leaderboard_best_per_user_ties_by_time_baselines_and_csv(
    client: TestClient, setup: dict[str, dict[str, str]], db: Session
) -> None:
    alice, bob, root = setup["alice"], setup["bob"], setup["judge"]
    a1 = submit(client, alice)
    finish(db, int(a1["id"]), [True, False])  # type: ignore[call-overload]
    a2 = submit(client, alice)
    finish(db, int(a2["id"]), [True, True])  # type: ignore[call-overload]
    b1 = submit(client, bob)
    finish(db, int(b1["id"]), [True, True])  # type: ignore[call-overload]
    r1 = submit(client, root)
    finish(db, int(r1["id"]), [False, False])  # type: ignore[call-overload]
    assert (
        client.patch(
            f"{API}/submissions/{r1['id']}", json={"baseline": True}, headers=root
        ).status_code
        == 200
    )
    board = client.get(f"{API}/challenges/server-tiny/leaderboard?phase=dev").json()
    rows = [(r["rank"], r["username"], r["submission_id"], r["baseline"]) for r in board["items"]]
    assert rows == [
        (1, "alice", a2["id"], False),  # 1.0, earlier than bob's 1.0
        (2, "bob", b1["id"], False),
        (None, "judge", r1["id"], True),
    ]
    task = board["items"][0]["tasks"]["PickCube-v1"]
    assert task["success_rate"] == 1.0
    assert 0 < task["ci_low"] < 1.0
    # Hiding alice's best falls back to her next best; making it private does the same.
    hide = {"hidden": True, "reason": "the same image as her first"}
    client.patch(f"{API}/submissions/{a2['id']}", json=hide, headers=root)
    board = client.get(f"{API}/challenges/server-tiny/leaderboard").json()
    assert [(r["username"], r["submission_id"]) for r in board["items"][:2]] == [
        ("bob", b1["id"]),
        ("alice", a1["id"]),
    ]
    page = client.get(f"{API}/challenges/server-tiny/leaderboard?per_page=1&page=2").json()
    assert page["total"] == 3
    assert [r["username"] for r in page["items"]] == ["alice"]
    csv_text = client.get(f"{API}/challenges/server-tiny/leaderboard?format=csv")
    assert csv_text.headers["content-type"].startswith("text/csv")
    lines = csv_text.text.strip().splitlines()
    assert lines[0].startswith("rank,username,baseline,score")
    assert lines[1].startswith("1,bob,False,1.0000")


def test_ingestion_is_idempotent_and_refuses_stale_attempts(
    client: TestClient, setup: dict[str, dict[str, str]], db: Session
) -> None:
    s = submit(client, setup["alice"])
    sid = int(s["id"])  # type: ignore[call-overload]
    finish(db, sid, [True, False])
    # The same final report again: a no-op that says it holds.
    assert report_final(db, sid, 1, State.SUCCEEDED, "done", result=result_doc([True, False]))
    # A different final state cannot overwrite it.
    assert not report_final(db, sid, 1, State.FAILED, "late")
    db.commit()
    r = client.post(f"{API}/submissions/{sid}/rerun", headers=setup["judge"])
    assert r.status_code == 200
    assert r.json()["attempt"] == 2
    assert r.json()["state"] == "queued"
    from server.kit.errors import Conflict

    with pytest.raises(Conflict):
        report_state(db, sid, 1, State.RUNNING, "a late worker of attempt 1")
    history = db.scalars(
        select(Transition.to_state).where(Transition.submission_id == sid).order_by(Transition.id)
    ).all()
    assert history == [State.QUEUED, State.LAUNCHING, State.RUNNING, State.SUCCEEDED, State.QUEUED]
    board = client.get(f"{API}/challenges/server-tiny/leaderboard").json()
    assert board["total"] == 0  # the re-run's result is not in yet


def test_internal_api_needs_the_worker_token(
    client: TestClient, setup: dict[str, dict[str, str]]
) -> None:
    s = submit(client, setup["alice"])
    token = client.app.state.services.settings.secret("worker_token")  # type: ignore[attr-defined]
    worker = {"Authorization": f"Bearer {token}"}
    claims, claim = "/internal/v1/claims", {"worker": "w1"}
    assert client.post(claims, json=claim).status_code == 401
    assert client.post(claims, json=claim, headers=setup["alice"]).status_code == 401
    claimed = client.post(claims, json=claim, headers=worker)
    assert claimed.status_code == 200
    assert (claimed.json()["submission_id"], claimed.json()["attempt"]) == (s["id"], 1)
    url = f"/internal/v1/submissions/{s['id']}/attempts/1/running"
    body = {"reason": "go", "deadline_s": 60}
    assert client.post(url, json=body).status_code == 401
    assert client.post(url, json=body, headers=setup["alice"]).status_code == 401
    ok = client.post(url, json=body, headers=worker)
    assert ok.status_code == 200
    assert ok.json() == {"applied": True, "state": "running"}
    assert "/internal" not in client.get("/openapi.json").text


def test_two_workers_racing_one_submission_exactly_one_wins(
    committed_sessions: sessionmaker[Session],
) -> None:
    with committed_sessions() as db:
        make_challenge(db)
        user = make_user(db, "racer")
        from server.challenges.service import get_challenge, get_phase
        from server.submissions.service import Resolved
        from server.submissions.service import submit as do_submit

        challenge = get_challenge(db, slug="server-tiny")
        s = do_submit(
            db,
            user=user,
            challenge=challenge,
            phase=get_phase(challenge, "dev"),
            image=IMAGE,
            description="",
            public=True,
            resolve=lambda _i: Resolved(pinned="x@sha256:" + "0" * 64, size_bytes=1),
        )
        db.commit()
        sid = s.id
    barrier = threading.Barrier(8)
    wins: list[bool] = []

    def take() -> None:
        with committed_sessions() as db:
            barrier.wait()
            won = transition(db, sid, 1, State.LAUNCHING, "mine")
            db.commit()
            wins.append(won)

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(wins) == [False] * 7 + [True]
    with committed_sessions() as db:
        assert db.get(Submission, sid).state == State.LAUNCHING  # type: ignore[union-attr]
        n = db.scalars(select(Transition).where(Transition.submission_id == sid)).all()
        assert len(n) == 2
