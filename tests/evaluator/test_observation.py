import numpy as np
import pytest

from evaluator.conditions import ConditionRuntime
from evaluator.observation import ObservationKeys
from evaluator.suite import ActionDelay, Condition, Nominal


def rgbd_obs() -> dict[str, object]:
    """The shape of PickCube-v1's rgbd observation (mani-skill 3.0.1), with tiny arrays."""
    return {
        "agent": {"qpos": np.zeros(9), "qvel": np.zeros(9)},
        "extra": {"is_grasped": np.array(False), "tcp_pose": np.zeros(7), "goal_pos": np.zeros(3)},
        "sensor_param": {
            "base_camera": {"intrinsic_cv": np.eye(3), "extrinsic_cv": np.zeros((3, 4))}
        },
        "sensor_data": {
            "base_camera": {
                "rgb": np.zeros((2, 2, 3), np.uint8),
                "depth": np.zeros((2, 2, 1), np.int16),
                "segmentation": np.zeros((2, 2, 1), np.int16),
            }
        },
    }


def paths(tree: object, prefix: str = "") -> set[str]:
    if not isinstance(tree, dict):
        return {prefix}
    return {p for key, value in tree.items() for p in paths(value, f"{prefix}/{key}".lstrip("/"))}


def test_named_entries_come_whole_and_everything_else_is_dropped():
    keys = ObservationKeys(["agent", "extra/tcp_pose", "sensor_data/*/rgb"])
    assert paths(keys.observation(rgbd_obs())) == {
        "agent/qpos",
        "agent/qvel",
        "extra/tcp_pose",
        "sensor_data/base_camera/rgb",
    }


def test_a_star_matches_any_one_name_and_a_branch_left_empty_disappears():
    keys = ObservationKeys(["sensor_*/*/depth", "pointcloud/xyzw"])
    assert keys.observation(rgbd_obs()).keys() == {"sensor_data"}
    assert paths(keys.observation(rgbd_obs())) == {"sensor_data/base_camera/depth"}


def test_no_keys_keep_the_observation_as_it_is():
    obs = rgbd_obs()
    assert ObservationKeys(None).observation(obs) is obs


def test_keys_cannot_select_from_a_flat_observation():
    with pytest.raises(ValueError, match="flat"):
        ObservationKeys(["agent"]).observation(np.zeros(3))


def test_the_spec_describes_only_the_entries_the_policy_sees():
    space = {
        "agent": {"qpos": {"shape": [9], "dtype": "float32"}},
        "extra": {
            "is_grasped": {"shape": [], "dtype": "bool"},
            "tcp_pose": {"shape": [7], "dtype": "float32"},
        },
    }
    kept = ObservationKeys(["agent/qpos", "extra/tcp_pose"]).space(space)
    assert kept == {
        "agent": {"qpos": {"shape": [9], "dtype": "float32"}},
        "extra": {"tcp_pose": {"shape": [7], "dtype": "float32"}},
    }


@pytest.mark.parametrize("params", [Nominal(), ActionDelay(steps=2)])
def test_every_observation_of_an_episode_is_narrowed_whatever_the_condition(params):
    runtime = ConditionRuntime(
        Condition(name="c", params=params), keys=ObservationKeys(["agent/qpos"])
    )
    seen = [runtime.begin_episode(1, rgbd_obs())]
    seen += [runtime.observe(rgbd_obs()) for _ in range(3)]
    assert all(paths(obs) == {"agent/qpos"} for obs in seen)
