"""The visual track: what a policy receives there (no object pose, only the declared keys)."""

from __future__ import annotations

import json

import pytest

from evaluator.plan import build_plan
from evaluator.suite import load_suite
from tests.evaluator.conftest import run

pytestmark = pytest.mark.sim

# Reports what it was given, through the one channel a policy has back: its error message.
PEEKER = """
import json
from manieval_sdk import Policy, serve

def paths(tree, prefix="", leaf=lambda node: not isinstance(node, dict)):
    if leaf(tree):
        return [prefix]
    return [p for k, v in tree.items() for p in paths(v, f"{prefix}/{k}".lstrip("/"), leaf)]

class Peek(Policy):
    def act(self, obs):
        seen = {
            "obs": sorted(paths(obs)),
            "space": sorted(paths(self.spec.observation_space, leaf=lambda n: "shape" in n)),
            "obs_mode": self.spec.obs_mode,
            "instruction": self.spec.instruction,
        }
        raise ValueError(json.dumps(seen))

serve(Peek())
"""

ARM = {"agent/qpos", "agent/qvel", "extra/tcp_pose"}
CAMERA = {
    f"sensor_param/base_camera/{name}" for name in ("intrinsic_cv", "extrinsic_cv", "cam2world_gl")
}
IMAGES = {"sensor_data/base_camera/rgb", "sensor_data/base_camera/depth"}
CLOUD = {"pointcloud/xyzw", "pointcloud/rgb"}


def test_a_visual_policy_sees_the_declared_keys_and_no_object_pose(make_policy):
    suite = load_suite("maniskill-visual")
    plan = build_plan(
        suite,
        "dev",
        tasks=["PickCube-v1", "PushCube-v1"],
        conditions=["nominal", "pointcloud"],
        episodes=1,
    )
    result = run(plan, make_policy(PEEKER))
    seen = {}
    for condition in result.conditions:
        for task in condition.tasks:
            (episode,) = task.episodes
            assert episode.failure_reason is not None
            report = episode.failure_reason.partition("ValueError: ")[2]
            seen[condition.name, task.env_id] = json.loads(report)
    goal = {"extra/goal_pos"}  # PickCube's goal is hidden from the camera; PushCube's is not
    assert {key: set(s["obs"]) for key, s in seen.items()} == {
        ("nominal", "PickCube-v1"): ARM | goal | CAMERA | IMAGES,
        ("nominal", "PushCube-v1"): ARM | CAMERA | IMAGES,
        ("pointcloud", "PickCube-v1"): ARM | goal | CAMERA | CLOUD,
        ("pointcloud", "PushCube-v1"): ARM | CAMERA | CLOUD,
    }
    for s in seen.values():
        assert s["space"] == s["obs"]  # the spec describes exactly what comes
        assert not [p for p in s["obs"] if p.endswith("_pose") and p != "extra/tcp_pose"]
    assert {key: s["obs_mode"] for key, s in seen.items()} == {
        ("nominal", "PickCube-v1"): "rgbd",
        ("nominal", "PushCube-v1"): "rgbd",
        ("pointcloud", "PickCube-v1"): "pointcloud",
        ("pointcloud", "PushCube-v1"): "pointcloud",
    }
    instructions = {t.env_id: t.instruction for t in suite.tasks}
    assert {key: s["instruction"] for key, s in seen.items()} == {
        key: instructions[key[1]] for key in seen
    }
