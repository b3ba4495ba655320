"""The whole path of an image submission: API, registry pinning, the embedded worker (over
loopback HTTP, configured by the environment as `manieval serve`'s is), docker executor."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from manieval.service import Service
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from testkit.factories import PASSWORD, SUITE, token_for
from testkit.waiting import poll
from tests.evaluator.conftest import SCRIPTED
from tests.server.registry_fixture import LocalRegistry, fixture_registry  # noqa: F401
from tests.worker.container_fixtures import (  # noqa: F401 - pytest fixtures
    ContainerEngine,
    PolicyImages,
    fixture_container_engine,
    fixture_policy_images,
    policy_containers,
)

pytestmark = pytest.mark.sim
API = "/api/v1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def service(
    tmp_path: Path,
    registry: LocalRegistry,
    container_engine: ContainerEngine,
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[httpx.Client]:
    # The embedded worker reads its own settings from the same environment as the server.
    monkeypatch.setenv("MANIEVAL_DOCKER_ENGINE_URL", container_engine.url)
    monkeypatch.setenv("MANIEVAL_POLICY_MEMORY_MIB", "512")
    settings = Settings(
        dev_mode=True,
        data_dir=tmp_path,
        cookie_secure=False,
        allowed_registries=[registry.domain],
        insecure_registries=[registry.domain],
    )
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        load_challenge(db, SUITE, ChallengeOptions(), seed_secret=settings.secret("seed_secret"))
    service = Service(settings, port=free_port(), sessions=sessions)
    assert service.start(), "the service did not start"
    assert service.worker is not None
    assert service.worker.settings.docker_engine_url == container_engine.url
    try:
        with httpx.Client(base_url=service.url, timeout=60) as client:
            client.post(
                f"{API}/users",
                json={"username": "alice", "email": "a@example.org", "password": PASSWORD},
            ).raise_for_status()
            client.headers.update(token_for(client, "alice"))  # type: ignore[arg-type]
            yield client
    finally:
        service.stop()


def test_an_image_submission_runs_in_a_container_and_leaves_nothing(
    service: httpx.Client, policy_images: PolicyImages, container_engine: ContainerEngine
) -> None:
    pinned = policy_images.publish("scripted", (SCRIPTED / "policy.py").read_text())
    tag = pinned.split("@")[0] + ":latest"
    r = service.post(f"{API}/submissions", json={"challenge": "server-tiny", "image": tag})
    assert r.status_code == 202, r.text
    assert r.json()["pinned_image"] == pinned
    sid = r.json()["id"]
    body = poll(
        lambda: service.get(f"{API}/submissions/{sid}").json(),
        lambda body: body["state"] in ("succeeded", "failed", "error", "cancelled", "timed_out"),
        f"submission {sid} to end",
        timeout=240,
    )
    assert body["state"] == "succeeded", body
    assert {t["condition"] for t in body["tasks"]} == {"nominal", "obs_noise"}
    # The engine removes the container as the run ends, which may be just after the report.
    poll(
        lambda: policy_containers(container_engine, submission=sid, attempt=1),
        lambda left: not left,
        "the policy container's removal",
        timeout=120,
    )
