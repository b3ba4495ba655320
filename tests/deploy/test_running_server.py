"""The probes, /metrics and the logs of a real `manieval serve` process, set up as in k8s/:
the Celery queue on Redis, JSON logs, a metrics token, and a schema migrated by someone else:
the migration Job, which holds the database URL and nothing else."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
from alembic.config import Config as AlembicConfig
from alembic.script import ScriptDirectory

from tests.cli.conftest import REPO, clean_environment, free_port
from tests.deploy import manifests
from tests.deploy.manifests import argv, container, one, render
from tests.worker.redis_server import Redis

TOKEN = "m" * 40


@pytest.fixture
def redis(tmp_path: Path) -> Iterator[Redis]:
    server = Redis(tmp_path / "redis")
    server.work.mkdir()
    server.start()
    yield server
    server.stop()


def environment(data_dir: Path, broker: str) -> dict[str, str]:
    return clean_environment() | {
        "MANIEVAL_DEV_MODE": "true",
        "MANIEVAL_DATA_DIR": str(data_dir),
        "MANIEVAL_QUEUE": "celery",
        "MANIEVAL_BROKER_URL": broker,
        "MANIEVAL_LOG_FORMAT": "json",
        "MANIEVAL_METRICS_TOKEN": TOKEN,
        "PYTHONUNBUFFERED": "1",
    }


def manieval(*args: str, env: Mapping[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "manieval", *args],
        env=dict(env),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )


@contextmanager
def serving(env: Mapping[str, str], log: Path) -> Iterator[str]:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with log.open("wb") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", "manieval", "serve", "--no-migrate", "--port", str(port)],
            env=dict(env),
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + 90
        while True:
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            try:
                if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
        yield url
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def test_the_api_refuses_a_schema_the_migration_has_not_brought_up(tmp_path: Path) -> None:
    env = environment(tmp_path, "redis://127.0.0.1:1/0")
    refused = manieval("serve", "--no-migrate", "--port", str(free_port()), env=env)
    assert refused.returncode == 3, refused.stdout + refused.stderr
    assert "manieval db upgrade" in refused.stderr
    assert manieval("db", "upgrade", env=env).returncode == 0


def test_probes_metrics_and_logs_of_a_running_server(tmp_path: Path, redis: Redis) -> None:
    env = environment(tmp_path, redis.url)
    assert manieval("db", "upgrade", env=env).returncode == 0
    log = tmp_path / "server.log"
    with serving(env, log) as url:
        assert httpx.get(f"{url}/healthz").json() == {"status": "ok"}
        ready = httpx.get(f"{url}/readyz")
        assert (ready.status_code, ready.json()) == (200, {"status": "ok"})

        assert httpx.get(f"{url}/metrics").status_code == 401
        wrong = httpx.get(f"{url}/metrics", headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401
        metrics = httpx.get(f"{url}/metrics", headers={"Authorization": f"Bearer {TOKEN}"})
        assert metrics.status_code == 200
        assert metrics.headers["content-type"].startswith("text/plain")
        lines = metrics.text.splitlines()
        assert "manieval_queue_depth 0.0" in lines
        assert "manieval_evaluations_running 0.0" in lines
        assert any(line.startswith("manieval_http_requests_total{") for line in lines)

        redis.stop()  # the broker goes away: not ready, but alive
        down = httpx.get(f"{url}/readyz")
        assert down.status_code == 503
        assert "broker" in down.json()
        assert httpx.get(f"{url}/healthz").status_code == 200
    records = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    access = [r for r in records if r["logger"] == "uvicorn.access"]
    assert any("/readyz" in r["message"] for r in access), log.read_text()
    assert all({"time", "level", "logger", "message"} <= r.keys() for r in records)


def test_the_migration_job_migrates_with_the_database_url_alone(tmp_path: Path) -> None:
    objects = render("dev")
    job = one(objects, "Job", "manieval-migrate")
    env = manifests.environment(objects, job, "migrate")
    assert set(env) == {"MANIEVAL_DATABASE_URL"}  # no secret key, seed secret, worker token
    database = tmp_path / "manieval.db"
    env["MANIEVAL_DATABASE_URL"] = f"sqlite:///{database}"  # the cluster's, replaced
    migrate = container(objects, "Job", "manieval-migrate", "migrate")
    words = argv(migrate)
    assert words[:3] == ["alembic", "-c", "/app/alembic.ini"]
    assert migrate["workingDir"] == "/app"  # the repository's root in the image
    words[2] = str(REPO / "alembic.ini")
    done = subprocess.run(
        [sys.executable, "-m", *words],
        env=clean_environment() | env | {"HOME": str(tmp_path)},
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    head = ScriptDirectory.from_config(AlembicConfig(str(REPO / "alembic.ini"))).get_current_head()
    with sqlite3.connect(database) as db:
        assert db.execute("SELECT version_num FROM alembic_version").fetchall() == [(head,)]
