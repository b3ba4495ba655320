"""What `create_app` wires around the pages: /metrics (optionally behind a token, HTTP metrics
by route template), /readyz with the Celery broker, and JSON errors for programs."""

from __future__ import annotations

import gc
import weakref

from fastapi.testclient import TestClient
from pydantic import SecretStr
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import Challenge
from testkit.factories import RecordingQueue, fake_resolve_for


def app_client(
    settings: Settings, sessions: sessionmaker[Session], **changes: object
) -> TestClient:
    changed = settings.model_copy(update=changes)
    app = create_app(
        changed,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(changed),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    return TestClient(app)


def test_metrics_count_requests_by_route_template_and_report_the_queue(
    client: TestClient, tiny: Challenge
) -> None:
    assert client.get("/challenges/server-tiny").status_code == 200
    assert client.get("/submissions/12345").status_code == 404
    body = client.get("/metrics")
    assert body.headers["content-type"].startswith("text/plain")
    text = body.text
    assert "manieval_queue_depth" in text
    assert 'route="/challenges/{slug}",status="2xx"' in text
    assert 'route="/submissions/{submission_id}",status="4xx"' in text
    assert "12345" not in text  # raw paths never become labels


def test_metrics_need_the_token_when_one_is_set(
    settings: Settings, sessions: sessionmaker[Session]
) -> None:
    secured = app_client(settings, sessions, metrics_token=SecretStr("m" * 40))
    refused = secured.get("/metrics")
    assert refused.status_code == 401
    assert refused.json()["error"]["code"] == "unauthorized"  # JSON, for programs
    assert secured.get("/metrics", headers={"Authorization": "Bearer wrong"}).status_code == 401
    ok = secured.get("/metrics", headers={"Authorization": "Bearer " + "m" * 40})
    assert ok.status_code == 200


def test_readiness_reports_an_unreachable_celery_broker(
    settings: Settings, sessions: sessionmaker[Session]
) -> None:
    assert app_client(settings, sessions).get("/readyz").json() == {"status": "ok"}
    broken = app_client(settings, sessions, queue="celery", broker_url="redis://127.0.0.1:1/0")
    r = broken.get("/readyz")
    assert r.status_code == 503
    assert r.json()["status"] == "unavailable"
    assert r.json()["broker"]


def test_an_app_that_is_dropped_is_freed(
    settings: Settings, sessions: sessionmaker[Session]
) -> None:
    """Nothing process-wide keeps an app alive once its last user lets go: FastAPI caches facts
    about every endpoint and dependency callable (strong references, thousands of entries), so
    a route function that closes over its app would keep each app ever made, and the test
    suite, which makes hundreds per process, grew by 14,000 objects a test."""
    app = _used_and_dropped(app_client(settings, sessions))
    gc.unfreeze()  # the first app of a process is frozen with what the process imported
    gc.collect()
    alive = app()
    assert alive is None, [type(r).__qualname__ for r in gc.get_referrers(alive)]


def _used_and_dropped(client: TestClient) -> weakref.ref[object]:
    with client:
        for path in ("/healthz", "/readyz", "/metrics", "/docs", "/api/v1/challenges"):
            assert client.get(path).status_code == 200, path
    return weakref.ref(client.app)
