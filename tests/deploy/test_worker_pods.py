"""The worker's and the reconciler's pods as k8s/ renders them, run for real: each container's
command line and environment (the dev overlay's, with the cluster's addresses replaced by a
private Redis and a stand-in for the server's internal API) as real Celery processes.

The evaluation worker consumes the queue the server sends wake-ups to and nothing else; the
reconciler consumes only its own queue, and the beat it embeds sends it a pass every 30 s; both
present the worker token, name themselves after their pod, and run on what their pod holds: no
database URL, no server secret.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import redis as redis_client
from celery import Celery

from internal_api.schemas import ReconcileOut, RestartOut, Silent
from internal_api.tasks import RECONCILE, RUN_NEXT
from tests.cli.conftest import REPO, clean_environment
from tests.deploy.manifests import (
    argv,
    container,
    containers,
    environment,
    one,
    option,
    render,
)
from tests.worker.redis_server import Redis
from worker.settings import WorkerSettings

EVALUATIONS_QUEUE = WorkerSettings.model_fields["celery_queue"].default
RECONCILE_QUEUE = WorkerSettings.model_fields["reconcile_queue"].default
SERVER_ONLY = {"MANIEVAL_DATABASE_URL", "MANIEVAL_SECRET_KEY", "MANIEVAL_SEED_SECRET"}
PATIENCE_S = 240.0  # generous: beat's first pass comes 30 s after the start, on a loaded machine


@dataclass
class Request:
    method: str
    path: str
    authorization: str
    body: object


@dataclass
class InternalAPI:
    """A stand-in for the server's /internal/v1: records every request, claims nothing."""

    url: str = ""
    requests: list[Request] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def seen(self, method: str, path: str) -> list[Request]:
        with self.lock:
            return [r for r in self.requests if r.method == method and r.path == path]

    def paths(self) -> set[str]:
        with self.lock:
            return {r.path for r in self.requests}


def _handler(api: InternalAPI) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def _answer(self) -> None:
            length = int(self.headers.get("Content-Length") or 0)
            raw = self.rfile.read(length) if length else b""
            with api.lock:
                api.requests.append(
                    Request(
                        self.command,
                        self.path,
                        self.headers.get("Authorization", ""),
                        json.loads(raw) if raw else None,
                    )
                )
            prefix = "/internal/v1"
            path = self.path.removeprefix(prefix)
            status, body = 404, "{}"
            if self.command == "POST" and path == "/claims":
                status, body = 204, ""
            elif self.command == "GET" and path == "/attempts/silent":
                status, body = 200, Silent(attempts=[]).model_dump_json()
            elif self.command == "POST" and path == "/reconcile":
                status, body = 200, ReconcileOut().model_dump_json()
            elif self.command == "POST" and path.startswith("/workers/"):
                status, body = 200, RestartOut(ended=[]).model_dump_json()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body.encode())

        do_GET = do_POST = _answer

        def log_message(self, format: str, *args: object) -> None:
            pass

    return Handler


@pytest.fixture
def internal_api() -> Iterator[InternalAPI]:
    api = InternalAPI()
    server = ThreadingHTTPServer(("127.0.0.1", 0), _handler(api))
    api.url = f"http://127.0.0.1:{server.server_address[1]}"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield api
    server.shutdown()
    server.server_close()
    thread.join(10)


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Redis]:
    server = Redis(tmp_path / "redis")
    server.work.mkdir()
    server.start()
    yield server
    server.stop()


def send(broker_url: str, task: str, queue: str) -> None:
    """A message as the server (or beat) sends it: a task name on a queue, nothing more."""
    app = Celery("test", broker=broker_url)
    app.conf.update(task_serializer="json", accept_content=["json"])
    args = [0, 0] if task == RUN_NEXT else []
    with app.connection_for_write() as connection:
        app.send_task(task, args=args, queue=queue, connection=connection)


def queued(broker_url: str, queue: str) -> int:
    with redis_client.Redis.from_url(broker_url) as r:
        return int(r.llen(queue))


@dataclass
class Pod:
    """A container of the dev overlay, run here: its command line and its environment."""

    words: list[str]
    env: dict[str, str]
    log: Path


def pod(name: str, container_name: str, tmp_path: Path, api: InternalAPI, broker: Redis) -> Pod:
    objects = render("dev")
    workload = one(objects, "Deployment", name)
    env = environment(objects, workload, container_name)
    assert not SERVER_ONLY & set(env), f"{name} holds {sorted(SERVER_ONLY & set(env))}"
    assert env["MANIEVAL_SERVER_URL"].startswith("http://manieval-api.")
    # The cluster's addresses and volumes, replaced by this test's.
    env |= {
        "MANIEVAL_SERVER_URL": api.url,
        "MANIEVAL_BROKER_URL": broker.url,
        "MANIEVAL_DATA_DIR": str(tmp_path / name),
    }
    words = argv(container(objects, "Deployment", name, container_name))
    for schedule in option(words, "--schedule", "-s"):
        assert schedule.startswith("/tmp/"), "the root filesystem is read-only: /tmp is mounted"
        words[words.index(schedule)] = str(tmp_path / "celerybeat-schedule")
    assert words[0] == "celery"
    return Pod(words, env, tmp_path / f"{name}.log")


Runner = Callable[[Pod], subprocess.Popen[bytes]]


@pytest.fixture
def run() -> Iterator[Runner]:
    started: list[subprocess.Popen[bytes]] = []

    def start(p: Pod) -> subprocess.Popen[bytes]:
        with p.log.open("wb") as out:
            process = subprocess.Popen(
                [sys.executable, "-m", *p.words],
                env=clean_environment() | p.env,
                cwd=REPO,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        started.append(process)
        return process

    yield start
    for process in started:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(10)


def wait_until(
    condition: Callable[[], bool], process: subprocess.Popen[bytes], log: Path, what: str
) -> None:
    deadline = time.monotonic() + PATIENCE_S
    while not condition():
        assert process.poll() is None, f"exited {process.returncode}:\n{log.read_text()}"
        assert time.monotonic() < deadline, f"{what}: not within {PATIENCE_S} s\n{log.read_text()}"
        time.sleep(0.2)


def test_the_containers_are_celery_workers_on_their_own_queues() -> None:
    for overlay in ("dev", "production", "gvisor"):
        objects = render(overlay)
        worker = argv(container(objects, "Deployment", "manieval-worker", "worker"))
        reconciler = argv(container(objects, "Deployment", "manieval-reconciler", "reconciler"))
        for words in (worker, reconciler):
            assert words[:4] == ["celery", "-A", "worker.celery_app", "worker"], overlay
        assert option(worker, "-Q", "--queues") == [EVALUATIONS_QUEUE], overlay
        assert option(reconciler, "-Q", "--queues") == [RECONCILE_QUEUE], overlay
        assert "--beat" in reconciler or "-B" in reconciler, overlay
        assert option(reconciler, "--concurrency", "-c") == ["1"], overlay
        # The beat schedule is written where the pod has a writable volume.
        (schedule,) = option(reconciler, "--schedule", "-s")
        spec = one(objects, "Deployment", "manieval-reconciler")["spec"]["template"]["spec"]
        (c,) = containers(spec)
        mounts = [m["mountPath"] for m in c["volumeMounts"]]
        assert any(schedule.startswith(m.rstrip("/") + "/") for m in mounts), schedule


def test_the_worker_pod_consumes_only_the_evaluations_queue(
    tmp_path: Path, internal_api: InternalAPI, broker: Redis, run: Runner
) -> None:
    p = pod("manieval-worker", "worker", tmp_path, internal_api, broker)
    # Waiting before it starts: a pass for the reconciler, and a wake-up for the workers.
    send(broker.url, RECONCILE, RECONCILE_QUEUE)
    send(broker.url, RUN_NEXT, EVALUATIONS_QUEUE)
    process = run(p)
    claims = "/internal/v1/claims"
    wait_until(lambda: bool(internal_api.seen("POST", claims)), process, p.log, "a claim")
    send(broker.url, RUN_NEXT, EVALUATIONS_QUEUE)  # consumed again, and still not the other
    wait_until(lambda: len(internal_api.seen("POST", claims)) >= 2, process, p.log, "claims")

    token = p.env["MANIEVAL_WORKER_TOKEN"]
    for claim in internal_api.seen("POST", claims):
        assert claim.authorization == f"Bearer {token}"
        assert claim.body == {"worker": "manieval-worker-pod"}  # the pod's name
    assert internal_api.seen("POST", "/internal/v1/workers/manieval-worker-pod/restarted")
    assert not internal_api.seen("POST", "/internal/v1/reconcile")
    assert queued(broker.url, RECONCILE_QUEUE) == 1, "the reconciler's pass is not the worker's"
    assert queued(broker.url, EVALUATIONS_QUEUE) == 0


def test_the_reconciler_pod_runs_its_passes_from_its_own_beat_and_nothing_else(
    tmp_path: Path, internal_api: InternalAPI, broker: Redis, run: Runner
) -> None:
    p = pod("manieval-reconciler", "reconciler", tmp_path, internal_api, broker)
    send(broker.url, RUN_NEXT, EVALUATIONS_QUEUE)  # waiting for an evaluation worker
    process = run(p)
    # Nobody sends it a pass here: its embedded beat does, on the reconcile queue.
    reconcile = "/internal/v1/reconcile"
    wait_until(lambda: bool(internal_api.seen("POST", reconcile)), process, p.log, "a pass")

    token = p.env["MANIEVAL_WORKER_TOKEN"]
    (restarted,) = internal_api.seen(
        "POST", "/internal/v1/workers/manieval-reconciler-pod/restarted"
    )
    for request in [*internal_api.seen("POST", reconcile), restarted]:
        assert request.authorization == f"Bearer {token}"
    # With the Kubernetes executor a pass first looks for silent attempts whose Job still runs.
    assert internal_api.seen("GET", "/internal/v1/attempts/silent")
    assert not internal_api.seen("POST", "/internal/v1/claims"), internal_api.paths()
    assert queued(broker.url, EVALUATIONS_QUEUE) == 1, "an evaluation's wake-up is not its own"
    assert (tmp_path / "celerybeat-schedule").exists() or any(tmp_path.glob("celerybeat-schedule*"))
