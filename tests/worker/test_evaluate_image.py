"""`manieval evaluate --image`: a participant runs their image the way a submission runs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from manieval.cli import app
from tests.evaluator.conftest import SCRIPTED
from tests.server.registry_fixture import fixture_registry  # noqa: F401 - pytest fixture
from tests.worker.container_fixtures import (  # noqa: F401 - pytest fixtures
    ContainerEngine,
    PolicyImages,
    fixture_container_engine,
    fixture_policy_images,
)

pytestmark = pytest.mark.sim
TINY = Path(__file__).resolve().parent.parent / "evaluator" / "tiny_suite.yaml"
runner = CliRunner()


def run(tmp_path: Path, *args: str) -> tuple[int, str, dict[str, object] | None]:
    out = tmp_path / "r.json"
    result = runner.invoke(
        app,
        [
            "evaluate",
            *args,
            "--suite",
            str(TINY),
            "--tasks",
            "PickCube-v1",
            "--episodes",
            "2",
            "--condition",
            "nominal",
            "--json",
            str(out),
        ],
    )
    doc = json.loads(out.read_text()) if out.exists() else None
    return result.exit_code, result.output, doc


def test_a_local_tag_and_a_pinned_reference_score_like_the_directory(
    tmp_path: Path, policy_images: PolicyImages, container_engine: ContainerEngine
) -> None:
    pinned = policy_images.publish("scripted", (SCRIPTED / "policy.py").read_text())
    code, output, expected = run(tmp_path, "--policy", str(SCRIPTED))
    assert code == 0, output
    assert expected is not None
    for image in (pinned, policy_images.local_tag("scripted")):
        code, output, doc = run(tmp_path, "--image", image, "--engine", container_engine.url)
        assert code == 0, output
        assert doc is not None
        assert str(doc["policy"]).startswith("image:")
        assert _same_episodes(doc, expected)  # same seeds, successes and lengths


def _same_episodes(a: dict[str, object], b: dict[str, object]) -> bool:
    def records(doc: dict[str, object]) -> list[tuple[object, ...]]:
        return [
            (e["seed"], e["success_once"], e["steps"])
            for c in doc["conditions"]  # type: ignore[attr-defined]
            for t in c["tasks"]
            for e in t["episodes"]
        ]

    return records(a) == records(b)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--image", "localhost/no-such-image:v1"], "no image"),
        (["--image", "x", "--policy", "examples/policies/scripted"], "exactly one"),
        ([], "exactly one"),
    ],
)
def test_clear_errors(
    tmp_path: Path, container_engine: ContainerEngine, args: list[str], message: str
) -> None:
    code, output, _ = run(tmp_path, *args, "--engine", container_engine.url)
    assert code == 2
    assert message in output
