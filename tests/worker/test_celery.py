"""Real `celery worker` processes on a real Redis take submissions from the API to the end,
and survive the faults the reconciler exists for."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app import create_app
from server.kit.settings import Settings
from server.models import State, Submission, Transition, utcnow
from tests.factories import PASSWORD, embedded_database, token_for
from tests.worker.redis_server import Redis
from worker.queue import CeleryQueue
from worker.reconcile import reconcile

pytestmark = pytest.mark.sim
API = "/api/v1"
FINAL = {"succeeded", "failed", "error", "cancelled", "timed_out"}


@pytest.fixture
def redis(tmp_path: Path) -> Iterator[Redis]:
    server = Redis(tmp_path)
    server.start()
    yield server
    server.stop()


@pytest.fixture
def env(tmp_path: Path, redis: Redis) -> dict[str, str]:
    return {
        **os.environ,
        "MANIEVAL_DEV_MODE": "true",
        "MANIEVAL_DATA_DIR": str(tmp_path / "data"),
        "MANIEVAL_ALLOW_LOCAL_POLICIES": "true",
        "MANIEVAL_QUEUE": "celery",
        "MANIEVAL_BROKER_URL": redis.url,
        "MANIEVAL_CELERY_QUEUE": f"test-{redis.port}",
    }


@pytest.fixture
def start_worker(env: dict[str, str]) -> Iterator[Callable[[], subprocess.Popen[bytes]]]:
    workers: list[subprocess.Popen[bytes]] = []

    def start() -> subprocess.Popen[bytes]:
        process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "celery",
                "-A",
                "worker.celery_app",
                "worker",
                "--pool",
                "solo",
                "--concurrency",
                "1",
                "--loglevel",
                "INFO",
                "--without-gossip",
                "--without-mingle",
                "-Q",
                env["MANIEVAL_CELERY_QUEUE"],
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        workers.append(process)
        return process

    yield start
    for process in workers:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(10)


@pytest.fixture
def api(env: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> Iterator[TestClient]:
    for key, value in env.items():
        if key.startswith("MANIEVAL_"):
            monkeypatch.setenv(key, value)
    settings = Settings()
    sessions = embedded_database(settings, quota_concurrent=5, quota_per_day=50)
    app = create_app(settings, sessions=sessions, background=False)
    app.state.sessions = sessions
    with TestClient(app) as client:
        client.post(
            f"{API}/users",
            json={"username": "alice", "email": "a@example.org", "password": PASSWORD},
        )
        client.headers.update(token_for(client, "alice"))
        yield client


def submit(client: TestClient, challenge: str = "server-tiny") -> int:
    r = client.post(f"{API}/submissions", json={"challenge": challenge, "image": "local:scripted"})
    assert r.status_code == 202, r.text
    return int(r.json()["id"])


def wait_for(client: TestClient, sid: int, states: set[str], timeout: float = 180) -> dict:  # type: ignore[type-arg]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"{API}/submissions/{sid}").json()
        if body["state"] in states:
            return body  # type: ignore[no-any-return]
        time.sleep(0.2)
    raise AssertionError(f"submission {sid} never reached {states}: {body}")


def test_a_celery_worker_takes_a_submission_to_succeeded(
    api: TestClient, start_worker: Callable[[], subprocess.Popen[bytes]]
) -> None:
    start_worker()
    sid = submit(api)
    body = wait_for(api, sid, FINAL)
    assert body["state"] == "succeeded", body
    assert {t["condition"] for t in body["tasks"]} == {"nominal", "obs_noise"}


def test_the_same_wake_up_twice_runs_one_evaluation(
    api: TestClient, start_worker: Callable[[], subprocess.Popen[bytes]], env: dict[str, str]
) -> None:
    sid = submit(api)
    queue = CeleryQueue(Settings())
    queue.enqueue(sid, 1)
    queue.enqueue(sid, 1)  # a duplicate delivery
    start_worker()
    assert wait_for(api, sid, FINAL)["state"] == "succeeded"
    time.sleep(2)  # let the duplicates be consumed
    sessions = api.app.state.sessions  # type: ignore[attr-defined]
    with sessions() as db:
        launches = db.scalars(
            select(Transition).where(
                Transition.submission_id == sid, Transition.to_state == State.LAUNCHING
            )
        ).all()
        assert len(launches) == 1


def test_a_killed_worker_is_reconciled_and_the_run_resumes_elsewhere(
    api: TestClient, start_worker: Callable[[], subprocess.Popen[bytes]]
) -> None:
    first = start_worker()
    sid = submit(api, "server-long")
    wait_for(api, sid, {"running"})
    os.killpg(first.pid, signal.SIGKILL)  # the worker and its policy process die mid-run
    first.wait(10)
    sessions = api.app.state.sessions  # type: ignore[attr-defined]
    report = reconcile(sessions, CeleryQueue(Settings()), now=utcnow() + timedelta(minutes=4))
    assert report.lost == [sid]
    assert report.requeued == [sid]
    start_worker()
    body = wait_for(api, sid, {"running"})
    assert body["attempt"] == 2
    cancelled = api.post(f"{API}/submissions/{sid}/cancel")
    assert cancelled.json()["state"] == "cancelled"
    with sessions() as db:
        s = db.get(Submission, sid)
        assert s is not None
        states = db.scalars(
            select(Transition.to_state)
            .where(Transition.submission_id == sid)
            .order_by(Transition.id)
        ).all()
    assert states == [
        State.QUEUED,
        State.LAUNCHING,
        State.RUNNING,
        State.ERROR,
        State.QUEUED,
        State.LAUNCHING,
        State.RUNNING,
        State.CANCELLED,
    ]


def test_redis_restarted_during_a_run(
    api: TestClient, start_worker: Callable[[], subprocess.Popen[bytes]], redis: Redis
) -> None:
    start_worker()
    sid = submit(api)
    wait_for(api, sid, {"running", "succeeded"})
    redis.stop()
    redis.start()  # empty: it keeps nothing on disk
    assert wait_for(api, sid, FINAL)["state"] == "succeeded"
    second = submit(api)  # the worker reconnected and takes new work
    assert wait_for(api, second, FINAL, timeout=240)["state"] == "succeeded"
