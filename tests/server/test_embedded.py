"""The embedded default end to end: API, outbox, in-process worker, evaluator, leaderboard."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.kit.settings import Settings
from tests.factories import PASSWORD, embedded_database, token_for

API = "/api/v1"
pytestmark = pytest.mark.sim


@pytest.fixture
def embedded(tmp_path: Path) -> Iterator[TestClient]:
    settings = Settings(
        dev_mode=True, data_dir=tmp_path, cookie_secure=False, allow_local_policies=True
    )
    sessions = embedded_database(settings, quota_concurrent=3)
    with TestClient(create_app(settings, sessions=sessions)) as client:
        r = client.post(
            f"{API}/users",
            json={"username": "demo", "email": "demo@example.org", "password": PASSWORD},
        )
        assert r.status_code == 201
        yield client


def wait_final(
    client: TestClient,
    headers: dict[str, str],
    sid: int,
    timeout: float = 240,
) -> dict[str, object]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body: dict[str, object] = client.get(f"{API}/submissions/{sid}", headers=headers).json()
        if body["state"] in ("succeeded", "failed", "error", "cancelled", "timed_out"):
            return body
        time.sleep(0.2)
    raise AssertionError(f"submission {sid} did not finish in {timeout} s")


def test_local_policy_runs_to_succeeded_and_reaches_the_leaderboard(
    embedded: TestClient,
) -> None:
    headers = token_for(embedded, "demo")
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-tiny", "image": "local:scripted", "description": "scripted"},
    )
    assert r.status_code == 202, r.text
    body = wait_final(embedded, headers, r.json()["id"])
    assert body["state"] == "succeeded", body
    states = [t["to_state"] for t in body["transitions"]]  # type: ignore[union-attr]
    assert states == ["queued", "launching", "running", "succeeded"]
    assert {t["condition"] for t in body["tasks"]} == {"nominal", "obs_noise"}  # type: ignore[union-attr]
    episodes = embedded.get(f"{API}/submissions/{r.json()['id']}/episodes", headers=headers).json()
    assert episodes["total"] == 4  # 2 episodes x 2 conditions
    assert [e["seed"] for e in episodes["items"][:2]] == [0, 1]
    board = embedded.get(f"{API}/challenges/server-tiny/leaderboard").json()
    assert [row["submission_id"] for row in board["items"]] == [r.json()["id"]]


def test_unknown_local_policy_is_refused_on_the_field(embedded: TestClient) -> None:
    headers = token_for(embedded, "demo")
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-tiny", "image": "local:does-not-exist"},
    )
    assert r.status_code == 422
    assert "one of:" in r.json()["error"]["fields"]["image"]


def test_cancel_stops_a_running_evaluation(embedded: TestClient) -> None:
    headers = token_for(embedded, "demo")
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-long", "phase": "test", "image": "local:random"},
    )
    sid = r.json()["id"]
    deadline = time.monotonic() + 120
    while embedded.get(f"{API}/submissions/{sid}", headers=headers).json()["state"] != "running":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    cancelled = embedded.post(f"{API}/submissions/{sid}/cancel", headers=headers)
    assert cancelled.status_code == 200
    assert cancelled.json()["state"] == "cancelled"
    idle = embedded.app.state.inline_queue.idle  # type: ignore[attr-defined]
    assert idle.wait(60), "the worker kept running after the cancel"
    body = wait_final(embedded, headers, sid)
    assert body["state"] == "cancelled"
    assert body["reason"] == "cancelled by its owner"


def test_a_crashing_policy_ends_failed_with_its_log_for_the_owner_only(
    embedded: TestClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import worker.run

    policies = tmp_path / "policies"
    (policies / "crasher").mkdir(parents=True)
    (policies / "crasher" / "policy.py").write_text(
        "import sys\nprint('loading weights... out of luck', file=sys.stderr)\nsys.exit(3)\n"
    )
    monkeypatch.setattr(worker.run, "EXAMPLES_DIR", policies)
    headers = token_for(embedded, "demo")
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-tiny", "image": "local:crasher"},
    )
    assert r.status_code == 202, r.text
    body = wait_final(embedded, headers, r.json()["id"])
    assert body["state"] == "failed"
    assert "exit code 3" in str(body["reason"])
    logs = embedded.get(f"{API}/submissions/{r.json()['id']}/logs", headers=headers).json()
    assert "out of luck" in logs["log_tail"]
    assert embedded.get(f"{API}/submissions/{r.json()['id']}/logs").status_code == 404
