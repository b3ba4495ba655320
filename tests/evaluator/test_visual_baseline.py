"""The visual track's baseline: the scripted example, seeing only the camera, solves PickCube and
PushCube (a few dev seeds: camera frames are slow on a CPU)."""

from __future__ import annotations

import pytest

from evaluator.plan import build_plan
from evaluator.suite import load_suite
from tests.evaluator.conftest import SCRIPTED, run

pytestmark = [pytest.mark.sim, pytest.mark.long, pytest.mark.timeout(1200)]


def test_the_scripted_example_picks_and_pushes_from_the_camera_and_the_point_cloud():
    plan = build_plan(
        load_suite("maniskill-visual"),
        "dev",
        tasks=["PickCube-v1", "PushCube-v1"],
        conditions=["nominal", "pointcloud"],
        episodes=3,
    )
    result = run(plan, SCRIPTED)
    assert result.status == "completed"
    rates = {(c.name, t.env_id): t.success_rate for c in result.conditions for t in c.tasks}
    assert rates == {
        ("nominal", "PickCube-v1"): 1.0,
        ("nominal", "PushCube-v1"): 1.0,
        ("pointcloud", "PickCube-v1"): 1.0,
        ("pointcloud", "PushCube-v1"): 1.0,
    }
