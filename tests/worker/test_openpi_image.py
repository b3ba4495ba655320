"""A policy that is an openpi-protocol server, packaged in an image with the bridge, through the
docker executor: it scores as its policy does in-process, a request it fails fails one episode
with its message, and a server that never starts stops the evaluation with its output."""

from __future__ import annotations

import json
import random
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EvaluationResult, episode_records
from evaluator.sources import LocalDirectory
from evaluator.suite import ActionChunks
from tests.server.registry_fixture import fixture_registry  # noqa: F401 - pytest fixture
from tests.worker.container_fixtures import (  # noqa: F401 - pytest fixtures
    ContainerEngine,
    PolicyImages,
    fixture_container_engine,
    fixture_policy_images,
    policy_containers,
    untag,
)
from tests.worker.openpi_image import EXAMPLE, build_openpi_image, visual_track_in_small
from worker.containers import ContainerImage

pytestmark = [pytest.mark.sim, pytest.mark.long]

REFERENCE = Path(__file__).resolve().parents[1] / "evaluator" / "openpi_reference.py"
BRIDGE = ["python3", "-m", "manieval_sdk.openpi", "--mapping", "/opt/policy/mapping.toml"]
SERVICE = f"test-session-{uuid.uuid4().hex[:8]}"
# The visual track in small, with chunks of the server's length, all executed: the server is
# asked at steps 0 and 8 of each 12-step episode.
VISUAL = visual_track_in_small(
    "openpi-visual", episodes=2, action_chunks=ActionChunks(max_length=8)
)


@pytest.fixture(scope="module")
def openpi_image(
    policy_images: PolicyImages,
    container_engine: ContainerEngine,
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[str]:
    """The example's image, built as its README says (cached), under this module's own tag."""
    tag = policy_images.local_tag("openpi-example")
    yield build_openpi_image(container_engine.env, tmp_path_factory.mktemp("openpi"), tag=tag)
    untag(container_engine.env, tag)


@pytest.fixture
def ids() -> tuple[int, int]:
    """A (submission, attempt) pair no other test or session on this machine uses."""
    return random.randrange(10**6, 10**9), 1


def visual_plan() -> EvaluationPlan:
    return build_plan(VISUAL, "dev")


def published(policy_images: PolicyImages, openpi_image: str, name: str, *command: str) -> str:
    """The example's image, with another command when one is given, pinned in the registry."""
    cmd = f"CMD {json.dumps(list(command))}\n" if command else ""
    return policy_images.publish_built(name, f"FROM {openpi_image}\n{cmd}")


def in_container(
    image: str, ids: tuple[int, int], container_engine: ContainerEngine
) -> EvaluationResult:
    source = ContainerImage(
        image,
        submission=ids[0],
        attempt=ids[1],
        engine_url=container_engine.url,
        service=SERVICE,
    )
    result = evaluate(visual_plan(), source)
    assert policy_containers(container_engine, submission=ids[0], attempt=ids[1]) == []
    return result


def test_an_openpi_server_scores_in_its_container_as_its_policy_does_in_process(
    tmp_path: Path,
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    openpi_image: str,
    ids: tuple[int, int],
) -> None:
    image = published(policy_images, openpi_image, "openpi-server")
    served = in_container(image, ids, container_engine)
    assert served.status == "completed", served.abort
    assert [e.failure for c in served.conditions for t in c.tasks for e in t.episodes] == [
        None,
        None,
    ]

    # The same policy answering the bridge in-process: no WebSocket, codec, child or container.
    reference = tmp_path / "reference"
    reference.mkdir()
    shutil.copy(REFERENCE, reference / "policy.py")
    for name in ("serve_policy.py", "mapping.toml"):
        shutil.copy(EXAMPLE / name, reference / name)
    in_process = evaluate(visual_plan(), LocalDirectory(reference))
    assert in_process.status == "completed", in_process.abort
    assert episode_records(served) == episode_records(in_process)


def test_a_request_the_server_fails_fails_its_episode_with_the_servers_message(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    openpi_image: str,
    ids: tuple[int, int],
) -> None:
    server = "python3 /opt/policy/serve_policy.py --port 8000 --fail-on-call 2"
    image = published(policy_images, openpi_image, "openpi-fails", *BRIDGE, "--command", server)
    result = in_container(image, ids, container_engine)
    assert result.status == "completed", result.abort
    episodes = [e for c in result.conditions for t in c.tasks for e in t.episodes]
    assert [(e.failure, e.steps) for e in episodes] == [
        ("policy_error", 8),  # the first chunk ran; the server failed the second request
        (None, 12),  # the bridge connected again: the next episode ran whole
    ]
    reason = episodes[0].failure_reason or ""
    assert "the policy server failed: RuntimeError: inference 2 fails" in reason, reason


def test_a_server_that_exits_at_start_stops_the_evaluation_with_its_output(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    openpi_image: str,
    ids: tuple[int, int],
) -> None:
    server = "python3 -c 'import sys; sys.exit(\"no checkpoint at /opt/policy/weights\")'"
    image = published(policy_images, openpi_image, "openpi-exits", *BRIDGE, "--command", server)
    result = in_container(image, ids, container_engine)
    assert result.status == "aborted"
    assert result.abort is not None
    assert result.abort.kind == "policy_crashed", result.abort
    tail = result.abort.log_tail
    assert "no checkpoint at /opt/policy/weights" in tail
    assert "the policy server exited with code 1 before it answered on ws://127.0.0.1:8000" in tail
