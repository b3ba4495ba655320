"""The submit page tells a participant how to push their own policy into the service's registry
(their name and the registry filled in), says why images are refused when they are, and a
queued submission's page shows its place in the queue."""

from __future__ import annotations

import html
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import Challenge
from server.submissions.images import image_resolver
from server.submissions.service import ImageGate
from testkit.factories import FakeRegistry, RecordingQueue, make_user, queue_submission
from tests.web.helpers import browser, csrf_of

FORM = "/challenges/server-tiny/submit"
REGISTRY = "127.0.0.1:5000"


def app_client(
    settings: Settings, sessions: sessionmaker[Session], *, refusal: str | None = None
) -> TestClient:
    resolve = ImageGate(image_resolver(settings, FakeRegistry()), lambda: refusal)
    app = create_app(
        settings,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=resolve,
        limiter=MemoryRateLimiter(),
        background=False,
    )
    return TestClient(app, base_url="http://testserver")


@pytest.fixture
def registry_client(settings: Settings, sessions: sessionmaker[Session]) -> Iterator[TestClient]:
    with_registry = settings.model_copy(
        update={"registry_domain": REGISTRY, "allowed_registries": [REGISTRY]}
    )
    with app_client(with_registry, sessions) as c:
        yield c


def test_the_submit_page_shows_the_push_commands_for_this_user(
    registry_client: TestClient, db: Session, tiny: Challenge
) -> None:
    make_user(db, "alice")
    page = html.unescape(browser(registry_client, "alice").get(FORM).text)
    assert "manieval login -u alice --server http://testserver" in page
    assert "curl -fsSLO http://testserver/downloads/policy-template.tar.gz" in page
    assert "manieval push my-policy:v1 --challenge server-tiny --wait" in page
    assert f"podman login --tls-verify=false -u alice {REGISTRY}" in page
    assert f"podman push --tls-verify=false my-policy:v1 {REGISTRY}/alice/my-policy:v1" in page
    assert f"under {REGISTRY}/alice/ only" in " ".join(page.split()).replace("<code>", "").replace(
        "</code>", ""
    )


def test_the_form_accepts_the_pushed_reference(
    registry_client: TestClient, db: Session, tiny: Challenge
) -> None:
    make_user(db, "alice")
    alice = browser(registry_client, "alice")
    r = alice.post(
        FORM,
        data={
            "csrf_token": csrf_of(alice.get(FORM).text),
            "phase": "dev",
            "image": f"{REGISTRY}/alice/my-policy:v1",
            "description": "",
            "visibility": "public",
        },
    )
    assert r.status_code == 303, r.text
    page = alice.get(r.headers["location"]).text
    assert f"{REGISTRY}/alice/my-policy@sha256:" in page
    assert "next in the queue" in page.lower()


def test_without_an_engine_the_page_and_the_api_say_why_images_are_refused(
    settings: Settings, sessions: sessionmaker[Session], db: Session, tiny: Challenge
) -> None:
    reason = "podman is not installed (the operator runs: apt-get install -y podman)"
    make_user(db, "alice")
    with app_client(settings, sessions, refusal=reason) as c:
        alice = browser(c, "alice")
        assert reason in html.unescape(alice.get(FORM).text)
        token = c.post(
            "/api/v1/auth/token",
            json={"login": "alice", "password": "correct horse battery staple", "name": "t"},
        ).json()["token"]
        r = c.post(
            "/api/v1/submissions",
            json={"challenge": "server-tiny", "image": f"{REGISTRY}/alice/p:v1"},
            headers={"Authorization": f"Bearer {token}"},
        )
        assert r.status_code == 503
        assert r.json()["error"]["message"] == reason
        local = c.post(
            "/api/v1/submissions",
            json={"challenge": "server-tiny", "image": "local:scripted"},
            headers={"Authorization": f"Bearer {token}"},
        )
        assert local.status_code == 202, local.text


def test_a_queued_submission_page_shows_its_place(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    alice = make_user(db, "alice")
    bob = make_user(db, "bob")
    queue_submission(db, alice, tiny)
    queue_submission(db, alice, tiny)
    mine = queue_submission(db, bob, tiny)
    db.commit()
    page = browser(client, "bob").get(f"/submissions/{mine.id}").text
    assert "2nd in the queue" in page  # bob's comes before alice's second: users interleave
