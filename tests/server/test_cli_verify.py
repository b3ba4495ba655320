"""`manieval challenge verify` on real ManiSkill tasks (CPU PhysX): the core suite passes with
the bundled scripted policy, and a task whose success is out of reach fails, by name."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from evaluator import packages, pool
from evaluator.suite import load_suite
from evaluator.verification import problems, read_report
from manieval.cli import app
from tests.evaluator.conftest import SCRIPTED

pytestmark = [pytest.mark.sim, pytest.mark.long]

runner = CliRunner()
PACKAGES_DIR = Path(__file__).resolve().parents[1] / "data" / "task_packages"
# PickCube-v1 and the test package's broken copy of it, whose goal is out of the arm's reach.
BROKEN_SUITE = """
name: broken-pick
version: 1
packages: [manieval_test_tasks]
tasks:
  - {env_id: PickCube-v1, max_episode_steps: 60}
  - {env_id: PickCubeUnreachable-v1, max_episode_steps: 60}
phases:
  dev: {seeds: {kind: public, start: 0}}
"""
# The organizer's reference for it: the scripted policy, which takes the broken task for
# PickCube-v1 (as its author would: the task looks solvable).
REFERENCE = """
from manieval_sdk import serve
from scripted import SKILLS, ScriptedPolicy

SKILLS["PickCubeUnreachable-v1"] = SKILLS["PickCube-v1"]

if __name__ == "__main__":
    serve(ScriptedPolicy())
"""


def test_the_core_suite_passes_with_the_scripted_policy(tmp_path: Path) -> None:
    out = tmp_path / "core.verification.json"
    args = ["maniskill-core", "--reference", "scripted", "--episodes", "1", "--out", str(out)]
    r = runner.invoke(app, ["challenge", "verify", *args])
    assert r.exit_code == 0, r.output
    suite, _ = packages.pin(load_suite("maniskill-core"))
    for task in suite.tasks:
        assert task.env_id in r.output
    assert "verification passed" in r.output
    assert problems(read_report(out), suite, path=out) == []


def test_a_task_whose_success_is_unreachable_fails_verification_by_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.syspath_prepend(str(PACKAGES_DIR))
    # Warm evaluator processes that an earlier test left keep the path they were started
    # with: the 2-worker run needs fresh ones, which see the test package.
    pool.close_idle()
    suite = tmp_path / "broken-pick.yaml"
    suite.write_text(BROKEN_SUITE)
    reference = tmp_path / "reference"
    reference.mkdir()
    (reference / "scripted.py").write_text((SCRIPTED / "policy.py").read_text())
    (reference / "policy.py").write_text(REFERENCE)
    r = runner.invoke(
        app, ["challenge", "verify", str(suite), "--reference", str(reference), "--episodes", "1"]
    )
    assert r.exit_code == 1, r.output
    assert "failed: PickCubeUnreachable-v1: the reference solved 0 of 1 episodes" in r.output
    assert "failed: PickCube-v1" not in r.output
    assert "verification FAILED" in r.output
    report = read_report(tmp_path / "broken-pick.verification.json")
    assert report is not None
    assert [t.reference_successes for t in report.tasks] == [1, 0]
