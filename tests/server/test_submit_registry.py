"""Submitting through the API against a real OCI registry: tags are pinned to digests."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.submissions.images import image_resolver
from testkit.factories import RecordingQueue, make_challenge, make_user, token_for
from tests.server.registry_fixture import (  # noqa: F401 - pytest fixtures
    LocalRegistry,
    PushedImage,
    fixture_registry,
    free_port,
    push_image,
)

API = "/api/v1"


@pytest.fixture
def pushed(registry: LocalRegistry) -> PushedImage:
    with httpx.Client(base_url=registry.url, timeout=10) as http:
        return push_image(http, "team/policy", "v1", layer_sizes=[3000, 5000])


@pytest.fixture
def real_client(
    tmp_path: Path, registry: LocalRegistry, sessions: sessionmaker[Session]
) -> Iterator[TestClient]:
    down = f"127.0.0.1:{free_port()}"  # allowed, but nothing listens there
    settings = Settings(
        dev_mode=True,
        data_dir=tmp_path,
        cookie_secure=False,
        allowed_registries=[registry.domain, down],
        insecure_registries=[registry.domain, down],
        max_image_bytes=100_000,
        registry_timeout=2,
    )
    app = create_app(
        settings,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=image_resolver(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with sessions() as db:
        make_challenge(db, quota_concurrent=10)
        make_user(db, "alice")
    with TestClient(app) as client:
        client.headers.update(token_for(client, "alice"))
        client.headers["X-Down"] = down
        yield client


def post(client: TestClient, image: str) -> httpx.Response:
    return client.post(f"{API}/submissions", json={"challenge": "server-tiny", "image": image})


def test_tag_is_pinned_to_the_registry_digest(
    real_client: TestClient, registry: LocalRegistry, pushed: PushedImage
) -> None:
    r = post(real_client, f"{registry.domain}/team/policy:v1")
    assert r.status_code == 202, r.text
    assert r.json()["pinned_image"] == f"{registry.domain}/team/policy@{pushed.digest}"
    assert r.json()["image"] == f"{registry.domain}/team/policy:v1"


@pytest.mark.parametrize(
    ("image", "status", "needle"),
    [
        ("{reg}/team/policy:nope", 422, "not found"),
        ("{reg}/team/absent:v1", 422, "not found"),
        ("ghcr.io/team/policy:v1", 422, "allowed registry"),
        ("{reg}/Team/policy:v1", 422, "lowercase"),
        ("{down}/team/policy:v1", 503, "reach"),
    ],
)
def test_unresolvable_references_are_clear_errors(
    real_client: TestClient,
    registry: LocalRegistry,
    pushed: PushedImage,
    image: str,
    status: int,
    needle: str,
) -> None:
    ref = image.format(reg=registry.domain, down=real_client.headers["X-Down"])
    r = post(real_client, ref)
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert needle in error["fields"]["image"].lower(), error


def test_images_over_the_size_limit_are_refused(
    real_client: TestClient, registry: LocalRegistry
) -> None:
    with httpx.Client(base_url=registry.url, timeout=10) as http:
        push_image(http, "team/big", "v1", layer_sizes=[150_000])
    r = post(real_client, f"{registry.domain}/team/big:v1")
    assert r.status_code == 422
    assert "MB" in r.json()["error"]["message"]
