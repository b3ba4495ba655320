"""Real `celery worker` processes on a real Redis take submissions from the API to the end,
and survive the faults the reconciler exists for.

The server is a real HTTP server in this process (uvicorn, the Celery queue) on a fresh
Postgres database. The workers are `celery worker` subprocesses started with the broker URL,
the server's URL and the worker token only: no database URL, no secret key, no seed secret.
They reach the server through /internal/v1, as a worker on another machine does.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, cast

import httpx
import pytest
import redis as redis_client
from celery import Celery
from fastapi import FastAPI
from sqlalchemy import create_engine, select, text, update
from sqlalchemy.orm import Session, sessionmaker

import evaluator.bundled
from evaluator import packages
from internal_api.schemas import FINAL_STATES
from internal_api.tasks import RECONCILE
from manieval.service import Service
from server.kit.settings import Settings
from server.models import Cause, State, Submission, Transition, utcnow
from server.submissions.outbox import CeleryQueue
from server.submissions.reports import report_running
from server.submissions.work import claim_next
from testkit.factories import PASSWORD, embedded_database, fake_resolve_for
from testkit.waiting import poll, until
from testkit.workers import public_api
from tests.worker.celery_workers import (
    WORKER_KEYS,
    add_challenge,
    celery_worker,
    load_suite_file,
    wait_ready,
    worker_environment,
)
from tests.worker.redis_server import Redis, free_port

pytestmark = [pytest.mark.sim, pytest.mark.long]
REPO = Path(__file__).resolve().parents[2]
TASK_PACKAGES = REPO / "tests" / "data" / "task_packages"
FINAL = {state.value for state in FINAL_STATES}  # as the API spells them
STOP_S = 120.0  # a cancelled or lost run is left well within this (it would run for minutes)

# The `local:` policies of these tests: the bundled ones, one that crashes at once, and one
# that takes 0.25 s per action (its time budget runs out; a long run of it lasts for minutes).
CRASHER = "import sys\nprint('loading weights... out of luck', file=sys.stderr)\nsys.exit(3)\n"
SLEEPER = """
import time
import numpy as np
from manieval_sdk import Policy, serve

class Sleeper(Policy):
    def act(self, obs):
        time.sleep(0.25)
        return np.zeros(self.spec.action_shape, dtype=np.float32)

serve(Sleeper())
"""


@pytest.fixture(scope="module")
def policies(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("policies")
    for name in ("scripted", "random"):
        (directory / name).symlink_to(REPO / "examples" / "policies" / name)
    (directory / "crasher").mkdir()
    (directory / "crasher" / "policy.py").write_text(CRASHER)
    (directory / "sleeper").mkdir()
    (directory / "sleeper" / "policy.py").write_text(SLEEPER)
    return directory


def fresh_database(postgres_url: str) -> tuple[str, Callable[[], None]]:
    """A new, empty database on the machine of `postgres_url`, and how to drop it."""
    name = f"manieval_celery_{uuid.uuid4().hex[:12]}"
    admin = create_engine(
        postgres_url.rsplit("/", 1)[0] + "/postgres", isolation_level="AUTOCOMMIT"
    )
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))

    def drop() -> None:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()

    return postgres_url.rsplit("/", 1)[0] + f"/{name}", drop


@dataclass
class Cluster:
    """The server (in this process), its database, a private Redis and the workers."""

    settings: Settings
    service: Service
    sessions: sessionmaker[Session]
    redis: Redis
    api: httpx.Client
    policies: Path
    work: Path
    workers: list[subprocess.Popen[bytes]] = field(default_factory=list)
    logs: dict[int, Path] = field(default_factory=dict)

    @property
    def reconcile_queue(self) -> str:
        return f"reconcile-{self.redis.port}"

    def environment(self, name: str, **extra: str) -> dict[str, str]:
        return worker_environment(
            self.settings, server_url=self.service.url, data_dir=self.work / name, **extra
        )

    def start_worker(
        self, name: str | None = None, *, queues: str | None = None, wait: bool = True, **extra: str
    ) -> subprocess.Popen[bytes]:
        """A worker process; `name`: its stable MANIEVAL_WORKER_NAME (default: host-pid)."""
        label = name or f"worker-{len(self.workers)}"
        if name is not None:
            extra["MANIEVAL_WORKER_NAME"] = name
        env = self.environment(label, MANIEVAL_RECONCILE_QUEUE=self.reconcile_queue, **extra)
        log = self.work / f"{label}-{len(self.workers)}.log"
        process = celery_worker(
            env, queues=queues or self.settings.celery_queue, policies=self.policies, log=log
        )
        self.workers.append(process)
        self.logs[process.pid] = log
        if wait:
            wait_ready(process, log)
        return process

    def kill(self, process: subprocess.Popen[bytes]) -> None:
        """SIGKILL the worker and everything it started (policy, simulator processes)."""
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        process.wait(30)

    def submit(
        self, challenge: str = "server-tiny", image: str = "local:scripted", phase: str = "dev"
    ) -> int:
        r = self.api.post(
            "/submissions", json={"challenge": challenge, "image": image, "phase": phase}
        )
        assert r.status_code == 202, r.text
        return int(r.json()["id"])

    def get(self, sid: int) -> dict[str, Any]:
        r = self.api.get(f"/submissions/{sid}")
        assert r.status_code == 200, r.text
        body: dict[str, Any] = r.json()
        return body

    def wait_for(
        self, sid: int, done: Callable[[dict[str, Any]], bool], timeout: float = 300
    ) -> dict[str, Any]:
        return poll(lambda: self.get(sid), done, f"submission {sid}", timeout=timeout)

    def wait_state(self, sid: int, states: set[str], timeout: float = 300) -> dict[str, Any]:
        return self.wait_for(sid, lambda body: body["state"] in states, timeout)

    def history(self, sid: int) -> list[tuple[int, State, Cause | None]]:
        with self.sessions() as db:
            rows = db.execute(
                select(Transition.attempt, Transition.to_state, Transition.cause)
                .where(Transition.submission_id == sid)
                .order_by(Transition.id)
            ).all()
        return [(attempt, state, cause) for attempt, state, cause in rows]

    def states(self, sid: int) -> list[State]:
        return [state for _, state, _ in self.history(sid)]

    def submission(self, sid: int) -> Submission:
        with self.sessions() as db:
            found = db.get(Submission, sid)
            assert found is not None
            return found

    def send(self, task: str, queue: str, *args: object) -> None:
        """Send a task by name, as Celery beat or the server does."""
        app = Celery("manieval-test", broker=self.settings.broker_url)
        try:
            app.send_task(task, args=list(args), queue=queue)
        finally:
            app.close()


@pytest.fixture
def redis(tmp_path: Path) -> Iterator[Redis]:
    server = Redis(tmp_path)
    server.start()
    yield server
    server.stop()


@pytest.fixture
def cluster(
    tmp_path: Path,
    redis: Redis,
    postgres_url: str,
    policies: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[Cluster]:
    monkeypatch.setattr(evaluator.bundled, "EXAMPLES_DIR", policies)  # the server checks names
    url, drop = fresh_database(postgres_url)
    settings = Settings(
        dev_mode=True,
        data_dir=tmp_path / "server",
        database_url=url,
        queue="celery",
        broker_url=redis.url,
        celery_queue=f"test-{redis.port}",
        allow_local_policies=True,
        cookie_secure=False,
        register_rate="1000/minute",
        login_rate="1000/minute",
        token_rate="1000/minute",
        submit_rate="1000/minute",
        leaderboard_max_age=0,
    )
    sessions = embedded_database(settings, quota_concurrent=5, quota_per_day=50)
    add_challenge(settings, "server-budget", **{"budget_s: 300": "budget_s: 2"})
    service = Service(settings, port=free_port(), sessions=sessions)
    # Image submissions are pinned by a registry stand-in (the registry has its own tests).
    cast(FastAPI, service.server.config.app).state.services.resolve = fake_resolve_for(settings)
    assert service.start(), "the server did not start"
    api = public_api(service.url)
    r = api.post(
        "/users", json={"username": "alice", "email": "a@example.org", "password": PASSWORD}
    )
    assert r.status_code == 201, r.text
    r = api.post("/auth/token", json={"login": "alice", "password": PASSWORD})
    assert r.status_code == 201, r.text
    api.headers["Authorization"] = f"Bearer {r.json()['token']}"
    work = tmp_path / "workers"
    work.mkdir()
    cluster = Cluster(settings, service, sessions, redis, api, policies, work)
    try:
        yield cluster
    finally:
        for process in cluster.workers:
            cluster.kill(process)
        api.close()
        service.stop()
        sessions.kw["bind"].dispose()
        drop()


def children(process: subprocess.Popen[bytes]) -> list[int]:
    """The processes a worker started, and theirs (an evaluation's policy and simulator)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:  # gone meanwhile
                continue
            parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found, frontier = [], [process.pid]
    while frontier:
        below = [pid for pid, parent in parents.items() if parent in frontier]
        found += below
        frontier = below
    return found


def environment_of(process: subprocess.Popen[bytes]) -> dict[str, str]:
    """The environment the running process really has."""
    raw = Path(f"/proc/{process.pid}/environ").read_bytes()
    pairs = (item.decode().partition("=") for item in raw.split(b"\0") if item)
    return {key: value for key, _, value in pairs}


def wait_busy(process: subprocess.Popen[bytes], timeout: float = STOP_S) -> None:
    """Until the worker evaluates (its simulator processes are up)."""

    def tree() -> str:
        listed = subprocess.run(["ps", "-eo", "pid,ppid,pgid,args"], capture_output=True)
        return f"worker {process.pid} to evaluate:\n{listed.stdout.decode()}"

    until(lambda: children(process), tree, timeout=timeout, every=0.2)


def wait_idle(process: subprocess.Popen[bytes], timeout: float = STOP_S) -> None:
    """Until the worker runs no evaluation any more (none of its processes is left)."""
    poll(
        lambda: children(process),
        lambda left: not left,
        "the worker to evaluate nothing",
        timeout=timeout,
    )


def test_a_worker_without_database_or_secrets_ends_submissions_in_every_state(
    cluster: Cluster,
) -> None:
    worker = cluster.start_worker()
    env = environment_of(worker)
    assert {k for k in env if k.startswith("MANIEVAL_")} == WORKER_KEYS | {
        "MANIEVAL_RECONCILE_QUEUE"
    }
    succeeded = cluster.submit()
    failed = cluster.submit(image="local:crasher")
    timed_out = cluster.submit("server-budget", image="local:sleeper")
    error = cluster.submit(image="127.0.0.1:5000/alice/policy:v1")  # no engine on this worker

    body = cluster.wait_state(succeeded, FINAL)
    assert body["state"] == "succeeded", body
    assert {t["condition"] for t in body["tasks"]} == {"nominal", "obs_noise"}
    assert body["score"] is not None
    body = cluster.wait_state(failed, FINAL)
    assert body["state"] == "failed", body
    assert "exit code 3" in body["reason"]
    assert "out of luck" in cluster.api.get(f"/submissions/{failed}/logs").json()["log_tail"]
    body = cluster.wait_state(timed_out, FINAL)
    assert body["state"] == "timed_out", body
    assert "budget" in body["reason"]
    body = cluster.wait_state(error, FINAL)
    assert body["state"] == "error", body
    assert "no container engine is configured" in body["reason"]
    started = [State.QUEUED, State.LAUNCHING, State.RUNNING]
    assert cluster.states(succeeded) == [*started, State.SUCCEEDED]
    assert cluster.states(failed) == [*started, State.FAILED]
    assert cluster.states(timed_out) == [*started, State.TIMED_OUT]
    assert cluster.states(error) == [State.QUEUED, State.LAUNCHING, State.ERROR]  # never ran
    for sid in (succeeded, failed, timed_out, error):
        assert str(cluster.submission(sid).worker).endswith(f"-{worker.pid}")
    assert not list((cluster.work / "worker-0" / "spool").glob("*.json"))  # all delivered


def test_a_task_packages_task_is_evaluated_ranked_and_its_version_recorded(
    cluster: Cluster, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The test task package is a plain directory on the path of whoever loads or evaluates the
    # suite: the server, which checks its tasks, and the worker's evaluator (never the policy).
    monkeypatch.syspath_prepend(str(TASK_PACKAGES))
    load_suite_file(cluster.settings, TASK_PACKAGES / "suite.yaml")
    path = os.pathsep.join(filter(None, [str(TASK_PACKAGES), os.environ.get("PYTHONPATH")]))
    cluster.start_worker(PYTHONPATH=path)
    sid = cluster.submit("packaged-tiny")

    body = cluster.wait_state(sid, FINAL)
    assert body["state"] == "succeeded", body
    assert [(t["env_id"], t["episodes_ran"], t["success_rate"]) for t in body["tasks"]] == [
        ("KeepCubeInRing-v1", 2, 1.0)  # its own rule: a still arm keeps the cube in the ring
    ]
    version = packages.installed_version("manieval_test_tasks")
    assert body["provenance"]["packages"] == {"manieval_test_tasks": version}
    board = cluster.api.get("/challenges/packaged-tiny/leaderboard").json()
    assert [row["submission_id"] for row in board["items"]] == [sid]


def test_a_cancel_mid_run_stops_the_worker_and_stays_cancelled(cluster: Cluster) -> None:
    worker = cluster.start_worker()
    sid = cluster.submit("server-long", image="local:sleeper")  # minutes, unless stopped
    cluster.wait_state(sid, {"running"})
    wait_busy(worker)
    r = cluster.api.post(f"/submissions/{sid}/cancel")
    assert r.status_code == 200, r.text
    assert r.json()["state"] == "cancelled"
    wait_idle(worker)  # the worker stopped the evaluation
    after = cluster.submit()  # and takes the next one
    assert cluster.wait_state(after, FINAL)["state"] == "succeeded"
    body = cluster.get(sid)
    assert body["state"] == "cancelled", body
    assert body["reason"] == "cancelled by its owner"
    assert cluster.states(sid) == [State.QUEUED, State.LAUNCHING, State.RUNNING, State.CANCELLED]


def test_the_same_wake_up_twice_runs_one_evaluation(cluster: Cluster) -> None:
    sid = cluster.submit()  # the server sends its wake-up; no worker runs yet
    queue = CeleryQueue(cluster.settings.broker_url, cluster.settings.celery_queue)
    queue.enqueue(sid, 1)
    queue.enqueue(sid, 1)  # duplicate deliveries
    broker = redis_client.Redis.from_url(cluster.settings.broker_url)
    assert broker.llen(cluster.settings.celery_queue) == 3
    cluster.start_worker()
    assert cluster.wait_state(sid, FINAL)["state"] == "succeeded"
    until(
        lambda: not (broker.llen(cluster.settings.celery_queue) or broker.hlen("unacked")),
        "the duplicates to be consumed",
        timeout=120,
    )
    broker.close()
    assert cluster.states(sid) == [State.QUEUED, State.LAUNCHING, State.RUNNING, State.SUCCEEDED]


def age(cluster: Cluster, sid: int, by: timedelta = timedelta(minutes=10)) -> None:
    """As if the attempt's worker had not reported for `by` (past the heartbeat timeout)."""
    with cluster.sessions.begin() as db:
        db.execute(
            update(Submission)
            .where(Submission.id == sid)
            .values(heartbeat_at=utcnow() - by, updated_at=utcnow() - by)
        )


def running_at(body: dict[str, Any], attempt: int) -> datetime:
    return next(
        datetime.fromisoformat(t["at"])
        for t in body["transitions"]
        if t["attempt"] == attempt and t["to_state"] == "running"
    )


def test_a_killed_worker_is_reconciled_and_the_run_resumes_elsewhere(cluster: Cluster) -> None:
    first = cluster.start_worker()
    sid = cluster.submit("server-long")
    cluster.wait_state(sid, {"running"})
    assert cluster.submission(sid).worker.endswith(f"-{first.pid}")  # type: ignore[union-attr]
    second = cluster.start_worker()  # another machine, idle
    cluster.start_worker(queues=cluster.reconcile_queue)  # the reconciler's own worker
    killed_at, killed = utcnow(), time.monotonic()
    cluster.kill(first)  # the worker and its policy and simulator processes die mid-run
    # Its heartbeat stops; skip the 3 minutes after which the reconciler calls it lost.
    age(cluster, sid)
    cluster.send(RECONCILE, cluster.reconcile_queue)
    body = cluster.wait_for(sid, lambda b: b["attempt"] == 2 and b["state"] == "running")
    observed = time.monotonic() - killed
    recorded = (running_at(body, 2) - killed_at).total_seconds()
    print(
        f"\nSIGKILL to the new attempt's `running` (reconciler, heartbeat timeout skipped): "
        f"{observed:.1f} s observed, {recorded:.1f} s recorded"
    )
    assert cluster.submission(sid).worker.endswith(f"-{second.pid}")  # type: ignore[union-attr]
    cancelled = cluster.api.post(f"/submissions/{sid}/cancel")
    assert cancelled.json()["state"] == "cancelled"
    assert cluster.history(sid) == [
        (1, State.QUEUED, None),
        (1, State.LAUNCHING, None),
        (1, State.RUNNING, None),
        (1, State.ERROR, Cause.WORKER_LOST),
        (2, State.QUEUED, None),
        (2, State.LAUNCHING, None),
        (2, State.RUNNING, None),
        (2, State.CANCELLED, None),
    ]
    wait_idle(second)


def test_a_worker_restarted_under_its_name_ends_its_lost_run_at_once(cluster: Cluster) -> None:
    first = cluster.start_worker("node-a")
    sid = cluster.submit("server-long")
    cluster.wait_state(sid, {"running"})
    killed_at, killed = utcnow(), time.monotonic()
    cluster.kill(first)
    again = cluster.start_worker("node-a", wait=False)  # a StatefulSet pod comes back
    body = cluster.wait_for(sid, lambda b: b["attempt"] == 2 and b["state"] == "running")
    observed = time.monotonic() - killed
    recorded = (running_at(body, 2) - killed_at).total_seconds()
    print(
        f"\nSIGKILL to the new attempt's `running` (restarted under its name, worker start-up "
        f"included): {observed:.1f} s observed, {recorded:.1f} s recorded"
    )
    assert cluster.submission(sid).worker == "node-a"
    cluster.api.post(f"/submissions/{sid}/cancel")
    assert [(a, s, c) for a, s, c in cluster.history(sid) if s == State.ERROR] == [
        (1, State.ERROR, Cause.WORKER_RESTARTED)
    ]
    wait_idle(again)


def test_the_reconciler_runs_on_its_own_queue_while_every_worker_is_busy(
    cluster: Cluster,
) -> None:
    busy = cluster.start_worker()  # the only evaluation worker
    long_run = cluster.submit("server-long", image="local:sleeper")  # minutes
    cluster.wait_state(long_run, {"running"})
    stale = cluster.submit()  # claimed by a worker that then vanished
    with cluster.sessions() as db:
        assert claim_next(db, worker="vanished", max_running_per_user=5) == (stale, 1)
        assert report_running(db, stale, 1, reason="evaluating", deadline_s=3600)
        db.commit()
    age(cluster, stale)
    cluster.start_worker(queues=cluster.reconcile_queue)
    cluster.send(RECONCILE, cluster.reconcile_queue)
    cluster.wait_for(stale, lambda b: b["attempt"] == 2)
    assert (1, State.ERROR, Cause.WORKER_LOST) in cluster.history(stale)
    assert cluster.get(long_run)["state"] == "running"  # the pass did not wait for it
    wait_busy(busy, timeout=0)
    cluster.api.post(f"/submissions/{long_run}/cancel")
    assert cluster.wait_state(stale, FINAL)["state"] == "succeeded"  # run again, once


def test_redis_restarted_during_a_run(cluster: Cluster) -> None:
    cluster.start_worker()
    sid = cluster.submit()
    cluster.wait_state(sid, {"running", "succeeded"})
    cluster.redis.stop()
    cluster.redis.start()  # empty: it keeps nothing on disk
    assert cluster.wait_state(sid, FINAL)["state"] == "succeeded"
    second = cluster.submit()  # the worker reconnected and takes new work
    assert cluster.wait_state(second, FINAL, timeout=240)["state"] == "succeeded"
