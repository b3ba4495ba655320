"""Running verification (evaluator/verify.py): what it runs and how it names it. Whole runs on
real ManiSkill tasks: tests/server/test_cli_verify.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from evaluator.verify import policy_label, random_policy, reference_policy, verification_plan
from tests.evaluator.conftest import SCRIPTED, tiny_suite


def test_a_bundled_policy_is_named_the_same_on_every_machine(tmp_path: Path) -> None:
    assert policy_label(random_policy()) == "local:random"
    assert policy_label(tmp_path) == f"dir:{tmp_path.resolve()}"


def test_the_reference_is_a_policy_directory_or_a_bundled_policys_name(tmp_path: Path) -> None:
    assert reference_policy("scripted").resolve() == SCRIPTED.resolve()
    assert reference_policy(str(SCRIPTED)) == SCRIPTED
    with pytest.raises(ValueError, match=r"no policy\.py there, and no bundled policy"):
        reference_policy(str(tmp_path))


def test_verification_runs_every_task_under_the_first_condition_on_the_dev_seeds() -> None:
    plan = verification_plan(tiny_suite(), episodes=2)
    assert plan.phase == "dev"
    assert [(r.env_id, r.condition.name, r.seeds) for r in plan.runs] == [
        ("PickCube-v1", "nominal", (100, 101)),
        ("PushCube-v1", "nominal", (100, 101)),
    ]
    assert plan.videos == 0
