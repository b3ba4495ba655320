"""A challenge whose suite gives each policy a GPU, on a service that has none for policies:
its submissions are refused at once, with the reason, instead of queued to wait forever."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.settings import Settings
from server.models import Submission
from testkit.factories import RecordingQueue, gpu_suite, make_challenge, make_user, token_for
from tests.web.helpers import browser, csrf_of

API = "/api/v1"
IMAGE = "127.0.0.1:5000/team/policy:v1"
REASON = (
    "this challenge asks for 1 GPU per policy, and this service has none for policies "
    "(its operator sets MANIEVAL_POLICY_GPUS)"
)


@pytest.fixture
def settings(settings: Settings, request: pytest.FixtureRequest) -> Settings:
    """The shared settings, with `policy_gpus` from the test's parameter (default 0)."""
    return settings.model_copy(update={"policy_gpus": getattr(request, "param", 0)})


@pytest.fixture
def alice(client: TestClient, db: Session, tmp_path: Path) -> dict[str, str]:
    load_challenge(db, gpu_suite(tmp_path), ChallengeOptions(), seed_secret="s" * 32)
    make_challenge(db)  # server-tiny: no GPU asked for
    make_user(db, "alice")
    return token_for(client, "alice")


def post(client: TestClient, headers: dict[str, str], challenge: str) -> dict[str, object]:
    body = {"challenge": challenge, "phase": "dev", "image": IMAGE}
    r = client.post(f"{API}/submissions", json=body, headers=headers)
    return {"status": r.status_code, **r.json()}


def test_a_service_without_gpus_refuses_a_gpu_challenges_submissions_with_the_reason(
    client: TestClient, alice: dict[str, str], work: RecordingQueue, db: Session
) -> None:
    out = post(client, alice, "server-gpu")
    assert out["status"] == 409
    assert out["error"] == {"code": "gpus_unavailable", "message": REASON, "fields": {}}
    assert work.sent == []
    assert db.scalar(select(func.count()).select_from(Submission)) == 0
    assert post(client, alice, "server-tiny")["status"] == 202  # its other challenges take them


@pytest.mark.parametrize("settings", [1], indirect=True)
def test_a_service_with_a_gpu_for_policies_queues_them(
    client: TestClient, alice: dict[str, str], work: RecordingQueue
) -> None:
    out = post(client, alice, "server-gpu")
    assert out["status"] == 202, out
    assert work.sent == [(out["id"], 1)]


def test_the_submit_page_says_so_before_anything_is_submitted(
    client: TestClient, alice: dict[str, str]
) -> None:
    web = browser(client, "alice")
    page = web.get("/challenges/server-gpu/submit")
    assert page.status_code == 200
    assert 'id="gpus-refused"' in page.text
    assert REASON in page.text
    assert 'id="gpus-refused"' not in web.get("/challenges/server-tiny/submit").text
    form = {"phase": "dev", "image": IMAGE, "csrf_token": csrf_of(page.text)}
    refused = web.post("/challenges/server-gpu/submit", data=form)
    assert refused.status_code == 200  # the form again, with the message
    assert 'role="alert"' in refused.text
    assert REASON in refused.text
