"""A database that does not answer is a 503 with Retry-After, for the API and the pages alike:
the client (the CLI, a worker, a browser) is told to try again, and the log keeps one line."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.kit.db import make_engine, session_factory
from server.kit.security import new_secret
from server.kit.settings import Settings
from testkit.factories import RecordingQueue
from tests.worker.redis_server import free_port


@pytest.fixture
def unreachable(tmp_path: Path) -> TestClient:
    settings = Settings(
        dev_mode=True, data_dir=tmp_path, cookie_secure=False, database_retry_after_s=7
    )
    url = f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/nothing"  # nothing listens
    sessions = session_factory(make_engine(url, connect_args={"connect_timeout": 2}))
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    return TestClient(app, raise_server_exceptions=False)


def test_the_api_answers_503_with_retry_after(
    unreachable: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        r = unreachable.get("/api/v1/challenges")
    assert r.status_code == 503
    assert r.headers["Retry-After"] == "7"  # MANIEVAL_DATABASE_RETRY_AFTER_S
    assert r.json()["error"]["code"] == "unavailable"
    assert "Traceback" not in caplog.text


def test_a_submit_is_refused_with_503_not_500(unreachable: TestClient) -> None:
    r = unreachable.post(
        "/api/v1/submissions",
        json={"challenge": "x", "image": "local:scripted"},
        headers={"Authorization": f"Bearer {new_secret('token').plaintext}"},
    )
    assert r.status_code == 503, r.text
    assert "Retry-After" in r.headers


def test_a_page_is_a_503_page(unreachable: TestClient) -> None:
    r = unreachable.get("/", headers={"Accept": "text/html"})
    assert r.status_code == 503
    assert r.headers["content-type"].startswith("text/html")
    assert "try again" in r.text.lower()


def test_the_internal_api_answers_503_so_workers_retry(unreachable: TestClient) -> None:
    settings: Settings = unreachable.app.state.services.settings  # type: ignore[attr-defined]
    token = settings.secret("worker_token")
    r = unreachable.post(
        "/internal/v1/claims",
        json={"worker": "w1"},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert r.status_code == 503
    assert "Retry-After" in r.headers
