"""The embedded default end to end, composed as `manieval serve` composes it: the server in
uvicorn, its embedded worker reaching it over loopback HTTP (`/internal/v1`), the outbox,
the evaluator and the leaderboard."""

from __future__ import annotations

import signal
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import FINAL_STATES
from manieval.service import EMBEDDED_WORKER, Service
from server.app import create_app
from server.kit.db import make_engine, session_factory
from server.kit.settings import Settings
from server.models import Cause, Submission, Transition
from server.submissions.work import end_stopped
from testkit.factories import PASSWORD, embedded_database, token_for
from testkit.waiting import poll
from testkit.workers import server_api, worker_settings
from tests.cli.conftest import running_server
from worker.embedded import EmbeddedWorker

API = "/api/v1"
FINAL = {state.value for state in FINAL_STATES}  # as the API spells them
pytestmark = [pytest.mark.sim, pytest.mark.long]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_service(settings: Settings, sessions: sessionmaker[Session]) -> Service:
    """The service on a free port (another process may take a free port first: try again)."""
    for _ in range(5):
        service = Service(settings, port=free_port(), sessions=sessions)
        if service.start():
            return service
        service.stop()
    raise AssertionError("the service did not start")


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    settings = Settings(
        dev_mode=True, data_dir=tmp_path, cookie_secure=False, allow_local_policies=True
    )
    service = start_service(settings, embedded_database(settings, quota_concurrent=3))
    try:
        yield service
    finally:
        service.stop()


@pytest.fixture
def embedded(service: Service) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=service.url, timeout=60) as client:
        r = client.post(
            f"{API}/users",
            json={"username": "demo", "email": "demo@example.org", "password": PASSWORD},
        )
        assert r.status_code == 201, r.text
        yield client


def wait_final(
    client: httpx.Client,
    headers: dict[str, str],
    sid: int,
    timeout: float = 240,
) -> dict[str, Any]:
    return poll(
        lambda: submission(client, headers, sid),
        lambda body: body["state"] in FINAL,
        f"submission {sid} to end",
        timeout=timeout,
    )


def submission(client: httpx.Client, headers: dict[str, str], sid: int) -> dict[str, Any]:
    body: dict[str, Any] = client.get(f"{API}/submissions/{sid}", headers=headers).json()
    return body


def wait_running(
    client: httpx.Client, headers: dict[str, str], sid: int, *, attempt: int = 1
) -> dict[str, Any]:

    def running(body: dict[str, Any]) -> bool:
        assert body["state"] not in FINAL, body
        return body["state"] == "running" and body["attempt"] == attempt

    return poll(
        lambda: submission(client, headers, sid),
        running,
        f"submission {sid}'s attempt {attempt} to run",
        timeout=180,
        every=0.05,
    )


def test_local_policy_runs_to_succeeded_and_reaches_the_leaderboard(
    embedded: httpx.Client,
) -> None:
    headers = token_for(embedded, "demo")  # type: ignore[arg-type]
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-tiny", "image": "local:scripted", "description": "scripted"},
    )
    assert r.status_code == 202, r.text
    body = wait_final(embedded, headers, r.json()["id"])
    assert body["state"] == "succeeded", body
    states = [t["to_state"] for t in body["transitions"]]
    assert states == ["queued", "launching", "running", "succeeded"]
    assert {t["condition"] for t in body["tasks"]} == {"nominal", "obs_noise"}
    episodes = embedded.get(f"{API}/submissions/{r.json()['id']}/episodes", headers=headers).json()
    assert episodes["total"] == 4  # 2 episodes x 2 conditions
    assert [e["seed"] for e in episodes["items"][:2]] == [0, 1]
    board = embedded.get(f"{API}/challenges/server-tiny/leaderboard").json()
    assert [row["submission_id"] for row in board["items"]] == [r.json()["id"]]


def test_unknown_local_policy_is_refused_on_the_field(embedded: httpx.Client) -> None:
    headers = token_for(embedded, "demo")  # type: ignore[arg-type]
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-tiny", "image": "local:does-not-exist"},
    )
    assert r.status_code == 422
    assert "one of:" in r.json()["error"]["fields"]["image"]


def test_cancel_stops_a_running_evaluation(embedded: httpx.Client, service: Service) -> None:
    headers = token_for(embedded, "demo")  # type: ignore[arg-type]
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-long", "phase": "test", "image": "local:random"},
    )
    sid = r.json()["id"]
    body = wait_running(embedded, headers, sid)

    def one_done(body: dict[str, Any]) -> bool:
        assert body["state"] == "running", body
        return bool((body.get("progress") or {}).get("done"))

    body = poll(  # a busy machine's first episode, and its report
        lambda: submission(embedded, headers, sid), one_done, "an episode done", timeout=300
    )
    done = body["progress"]["done"]
    cancelled = embedded.post(f"{API}/submissions/{sid}/cancel", headers=headers)
    assert cancelled.status_code == 200
    assert cancelled.json()["state"] == "cancelled"
    assert service.worker is not None
    assert service.worker.queue.idle.wait(60), "the worker kept running after the cancel"
    body = wait_final(embedded, headers, sid)
    assert body["state"] == "cancelled"
    assert body["reason"] == "cancelled by its owner"
    # What ran before the cancel is kept (the worker reports it after the end), and only that:
    # no rate or interval over the episodes that never started.
    ran = sum(t["episodes_ran"] for t in body["tasks"])
    planned = sum(t["episodes"] for t in body["tasks"])
    assert done <= ran < planned, body["tasks"]
    for task in body["tasks"]:
        complete = task["episodes_ran"] == task["episodes"]
        assert (task["success_rate"] is None, task["ci_low"] is None) == (not complete,) * 2
    assert body["conditions"] == {}  # the first condition did not run to its end
    url = f"{API}/submissions/{sid}/episodes?per_page=200"
    episodes = embedded.get(url, headers=headers).json()
    assert episodes["total"] == ran
    assert all(e["failure"] != "the evaluation stopped before it" for e in episodes["items"])


def test_a_crashing_policy_ends_failed_with_its_log_for_the_owner_only(
    embedded: httpx.Client, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import evaluator.bundled

    policies = tmp_path / "policies"
    (policies / "crasher").mkdir(parents=True)
    (policies / "crasher" / "policy.py").write_text(
        "import sys\nprint('loading weights... out of luck', file=sys.stderr)\nsys.exit(3)\n"
    )
    monkeypatch.setattr(evaluator.bundled, "EXAMPLES_DIR", policies)
    headers = token_for(embedded, "demo")  # type: ignore[arg-type]
    r = embedded.post(
        f"{API}/submissions",
        headers=headers,
        json={"challenge": "server-tiny", "image": "local:crasher"},
    )
    assert r.status_code == 202, r.text
    body = wait_final(embedded, headers, r.json()["id"])
    assert body["state"] == "failed"
    assert "exit code 3" in str(body["reason"])
    assert body["tasks"]
    assert {t["episodes_ran"] for t in body["tasks"]} == {0}
    assert {t["success_rate"] for t in body["tasks"]} == {None}
    assert body["conditions"] == {}
    logs = embedded.get(f"{API}/submissions/{r.json()['id']}/logs", headers=headers).json()
    assert "out of luck" in logs["log_tail"]
    anonymous = embedded.get(f"{API}/submissions/{r.json()['id']}/logs")
    assert anonymous.status_code == 403  # the submission is public, its log its owner's only
    assert "out of luck" not in anonymous.text


# A restart ------------------------------------------------------------------------------------


STOPPED = ("interrupted: the service was stopped; queued again", Cause.STOPPED)
RESTARTED = ("the worker evaluating it restarted; queued again", Cause.WORKER_RESTARTED)


@pytest.mark.parametrize(
    ("stop", "expected"),
    [(signal.SIGINT, STOPPED), (signal.SIGTERM, STOPPED), (signal.SIGKILL, RESTARTED)],
    ids=["ctrl-c", "sigterm", "crash"],
)
def test_a_stopped_or_crashed_server_runs_its_runs_in_flight_again(
    tmp_path: Path, stop: signal.Signals, expected: tuple[str, Cause]
) -> None:
    # `manieval serve` in a process of its own: stopped (Ctrl-C, SIGTERM) or killed in the
    # middle of an evaluation, then started again on the same data. A stop interrupts the run
    # and records it as interrupted, queued again (every time); after a crash the embedded
    # worker, at its next start, tells the server it restarted (the run goes again once).
    # Either way the attempt ends `error` (ours: no quota) with its cause, and attempt 2 runs.
    reason, cause = expected
    data = tmp_path / "data"
    with httpx.Client(timeout=60) as http:
        with running_server(data, stop=stop) as first:
            http.base_url = httpx.URL(first.url)
            http.post(
                f"{API}/users",
                json={"username": "demo", "email": "demo@example.org", "password": PASSWORD},
            ).raise_for_status()
            headers = token_for(http, "demo")  # type: ignore[arg-type]
            r = http.post(
                f"{API}/submissions",
                headers=headers,
                json={"challenge": "server-long", "image": "local:random"},
            )
            assert r.status_code == 202, r.text
            sid = r.json()["id"]
            wait_running(http, headers, sid)
        with running_server(data, challenges=False) as second:
            http.base_url = httpx.URL(second.url)
            again = wait_running(http, headers, sid, attempt=2)
            ended = [t for t in again["transitions"] if t["attempt"] == 1][-1]
            assert ended["to_state"] == "error"
            assert ended["reason"] == reason
            assert [t["to_state"] for t in again["transitions"]] == [
                "queued",
                "launching",
                "running",
                "error",
                "queued",
                "launching",
                "running",
            ]
            assert http.post(f"{API}/submissions/{sid}/cancel", headers=headers).is_success
            assert wait_final(http, headers, sid)["state"] == "cancelled"
    database = Settings(dev_mode=True, data_dir=data, cookie_secure=False).resolved_database_url
    sessions = session_factory(make_engine(database))
    with sessions() as db:
        submission = db.get(Submission, sid)
        assert submission is not None
        assert submission.worker == EMBEDDED_WORKER
        causes = db.scalars(
            select(Transition.cause).where(
                Transition.submission_id == sid, Transition.cause.is_not(None)
            )
        ).all()
        assert causes == [cause]


def test_a_stopped_worker_interrupts_its_run_and_reports_nothing_of_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The worker stopping under a run (its first report held until the stop): the run stops
    # within seconds, its policy process gone, and nothing of it is reported or spooled: cut
    # short, it is no result of the policy's, and no error of ours to end it with. It stays
    # in flight for whoever stopped the worker to record (the service: `end_stopped`).
    settings = Settings(
        dev_mode=True, data_dir=tmp_path, cookie_secure=False, allow_local_policies=True
    )
    sessions = embedded_database(settings, quota_concurrent=3)
    wsettings = worker_settings(settings, worker_name=EMBEDDED_WORKER)
    worker = EmbeddedWorker(wsettings)
    app = create_app(settings, sessions=sessions, work=worker.queue)
    api = server_api(app, wsettings)
    reporting = threading.Event()
    progress, final = api.progress, api.final
    finals: list[Any] = []

    def held_until_stopped(*args: Any, **kwargs: Any) -> Any:
        reporting.set()
        api.stop.wait(300)
        return progress(*args, **kwargs)

    def recorded(*args: Any, **kwargs: Any) -> Any:
        finals.append(args)
        return final(*args, **kwargs)

    monkeypatch.setattr(api, "progress", held_until_stopped)
    monkeypatch.setattr(api, "final", recorded)
    with TestClient(app) as client:
        try:
            client.post(
                f"{API}/users",
                json={"username": "demo", "email": "demo@example.org", "password": PASSWORD},
            ).raise_for_status()
            headers = token_for(client, "demo")
            worker.start(api=api)
            r = client.post(
                f"{API}/submissions",
                headers=headers,
                json={"challenge": "server-long", "image": "local:random"},
            )
            assert r.status_code == 202, r.text
            sid = r.json()["id"]
            assert reporting.wait(240), "the run sent no progress"
            policies = _policy_processes()
            assert policies, "no policy process runs"
            assert worker.stop(timeout=60), "the run did not stop"
            assert not [p for p in policies if _alive(p)]
            assert finals == []
            assert list(api.spool) == []
            body = client.get(f"{API}/submissions/{sid}", headers=headers).json()
            assert (body["state"], body["attempt"]) == ("running", 1)
            with sessions.begin() as db:
                assert end_stopped(db, worker=EMBEDDED_WORKER) == [sid]
            body = client.get(f"{API}/submissions/{sid}", headers=headers).json()
            assert (body["state"], body["attempt"]) == ("queued", 2)
            assert body["reason"] == "interrupted: the service was stopped; queued again"
        finally:
            worker.stop(timeout=30)


def _policy_processes() -> list[psutil.Process]:
    """This process's policy processes (the sandbox and the policy in it)."""
    return [
        p
        for p in psutil.Process().children(recursive=True)
        if any("policy" in part for part in _cmdline(p))
    ]


def _cmdline(process: psutil.Process) -> list[str]:
    try:
        return process.cmdline()
    except psutil.Error:
        return []


def _alive(process: psutil.Process) -> bool:
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False
