"""Workers in tests: the real worker code, reaching a real app through /internal/v1.

The app runs in-process (Starlette's test client as the transport), so a test drives the
worker exactly as production does, claims, reports and all, and can still look at the
database behind the server.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.settings import Settings
from server.submissions.outbox import WorkQueue
from testkit.factories import RecordingQueue, fake_resolve_for
from worker.server_api import ServerAPI, Spool
from worker.settings import WorkerSettings


def worker_settings(settings: Settings, **overrides: Any) -> WorkerSettings:
    """A worker's settings for the server of `settings`: its token, its own data directory."""
    values: dict[str, Any] = {
        "worker_token": settings.secret("worker_token"),
        "worker_name": "test-worker",
        "data_dir": settings.data_dir / "worker",
        "allow_local_policies": True,
        "claim_patience_s": 30.0,
        "report_patience_s": 60.0,
    }
    return WorkerSettings(**(values | overrides))


def server_app(
    settings: Settings, sessions: sessionmaker[Session], work: WorkQueue | None = None
) -> FastAPI:
    """The server a test's workers report to (no background threads)."""
    return create_app(
        settings,
        sessions=sessions,
        work=work if work is not None else RecordingQueue(),
        resolve=fake_resolve_for(settings),
        background=False,
    )


def server_api(app: FastAPI, worker: WorkerSettings, *, spool: Path | None = None) -> ServerAPI:
    """The worker's client of `app`'s internal API, over an in-process transport."""
    http = TestClient(
        app,
        base_url="http://testserver/internal/v1",
        headers={"Authorization": f"Bearer {worker.worker_token.get_secret_value()}"},
        raise_server_exceptions=False,  # a bug in the app is a 500, as over a real socket
    )
    return ServerAPI(
        http,
        spool=Spool(spool or worker.resolved_spool_dir),
        claim_patience_s=worker.claim_patience_s,
        report_patience_s=worker.report_patience_s,
    )


def public_api(url: str) -> httpx.Client:
    """A client of a served instance's public API (`url`: its base), as a test's participant.

    A new connection per request: on a reused one, a request can meet the server's keep-alive
    closing it (uvicorn's 5 s), "connection reset by peer", when the test is descheduled for
    seconds between taking the connection and sending, as on a loaded machine."""
    return httpx.Client(
        base_url=f"{url}/api/v1", timeout=60, limits=httpx.Limits(max_keepalive_connections=0)
    )
