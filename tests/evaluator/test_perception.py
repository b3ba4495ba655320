"""The scripted baseline's eyes on the visual track (examples/policies/scripted/perception.py),
on synthetic views: no simulator."""

from __future__ import annotations

import importlib.util
import math
import sys
from types import ModuleType

import numpy as np
import pytest

from tests.evaluator.conftest import SCRIPTED


def load_perception() -> ModuleType:
    name = "scripted_perception"  # the example's module, under a name of its own here
    spec = importlib.util.spec_from_file_location(name, SCRIPTED / "perception.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


perception = load_perception()

# PickCube-v1's base camera (mani-skill 3.0.1): 128 px, 90 degrees, looking down at the table.
INTRINSIC = np.array([[64.0, 0.0, 64.0], [0.0, 64.0, 64.0], [0.0, 0.0, 1.0]])
EXTRINSIC = np.array(
    [
        [0.0, 1.0, 0.0, 0.0],
        [0.78086877, 0.0, -0.62469506, 0.14055645],
        [-0.62469506, 0.0, -0.78086877, 0.6559298],
    ]
)


def project(points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (u, v) and depth of world points, as the camera sees them."""
    camera = points @ EXTRINSIC[:, :3].T + EXTRINSIC[:, 3]
    uv = camera[:, :2] / camera[:, 2:] * INTRINSIC[0, 0] + INTRINSIC[0, 2]
    return np.column_stack([uv, camera[:, 2]])


def test_a_pixel_goes_back_to_the_world_point_it_shows():
    world = np.array([[-0.1, 0.05, 0.02], [0.05, -0.1, 0.0], [0.0, 0.0, 0.2]])
    seen = project(world)
    depth = np.zeros((128, 128, 1), dtype=np.int16)
    for u, v, d in seen:
        depth[int(v), int(u), 0] = round(d * 1000)
    xyz, valid = perception.back_project(depth, INTRINSIC, EXTRINSIC)
    hits = xyz[valid]
    assert len(hits) == len(world)
    for point in world:  # within a pixel and a millimetre of depth
        assert np.min(np.linalg.norm(hits - point, axis=1)) < 0.006


@pytest.mark.parametrize("yaw", [0.0, 0.3, -0.6, 1.2])
def test_a_cubes_centre_and_heading_come_from_its_top_face(yaw):
    centre = np.array([0.03, -0.07, 0.02])
    grid = np.linspace(-0.019, 0.019, 6)
    face = np.array([[x, y] for x in grid for y in grid])
    turn = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    top = np.column_stack([face @ turn.T + centre[:2], np.full(len(face), 0.04)])
    side = top[:6] - np.array([0.0, 0.0, 0.02])  # some of a side face, lower down
    found = perception.cube_pose(np.concatenate([top, side]))
    assert found is not None
    pos, heading = found
    assert np.linalg.norm(pos - centre) < 0.003
    quarter = math.pi / 2
    error = (heading - yaw + quarter / 2) % quarter - quarter / 2  # a square repeats
    assert abs(error) < 0.05


def test_no_cube_is_found_in_too_few_points():
    assert perception.cube_pose(np.zeros((2, 3))) is None


def test_colours_tell_the_cubes_and_the_target_from_the_table():
    colours = np.array(
        [
            [231, 4, 4],  # PickCube's red cube, lit
            [204, 71, 76],  # PushCube's target
            [58, 102, 187],  # PushCube's blue cube
            [3, 231, 3],  # StackCube's green cube
            [116, 69, 42],  # the wooden table
        ],
        dtype=float,
    )
    assert perception.pure_red(colours).tolist() == [True, False, False, False, False]
    assert perception.target_red(colours).tolist() == [True, True, False, False, False]
    assert perception.cube_blue(colours).tolist() == [False, False, True, False, False]
    assert perception.pure_green(colours).tolist() == [False, False, False, True, False]


def test_a_held_cube_moves_with_the_hand_and_is_looked_for_again_once_let_go():
    track = perception.CubeTrack(perception.pure_red, grasped=True, still=True)
    red = np.array([[231.0, 4.0, 4.0]])

    def seen_at(x: float) -> tuple[np.ndarray, np.ndarray]:
        top = np.array([[x + dx, dy, 0.04] for dx in (-0.015, 0.015) for dy in (-0.015, 0.015)])
        return top, np.repeat(red, len(top), axis=0)

    track.update(*seen_at(0.0), perception.Hand(pos=np.array([0.0, 0.0, 0.3]), width=0.08))
    assert np.allclose(track.pos, [0.0, 0.0, 0.02])
    closing = perception.Hand(pos=np.array([0.0, 0.0, 0.025]), width=0.05)
    track.update(*seen_at(0.0), closing)
    lifted = perception.Hand(pos=np.array([0.1, 0.0, 0.2]), width=0.04)
    track.update(np.zeros((0, 3)), np.zeros((0, 3)), lifted)  # out of sight in the hand
    assert np.allclose(track.pos, [0.1, 0.0, 0.195])
    track.update(*seen_at(0.2), perception.Hand(pos=np.array([0.1, 0.0, 0.2]), width=0.08))
    assert np.allclose(track.pos, [0.2, 0.0, 0.02])  # let go: seen again where it fell


def test_nothing_is_handed_to_the_skill_until_every_object_has_been_seen():
    eyes = perception.Eyes("PushCube-v1")
    arm = {"agent": {"qpos": np.zeros(9)}, "extra": {"tcp_pose": np.array([0, 0, 0.3, 1, 0, 0, 0])}}
    blue = np.array([[-0.01, 0.0, 0.04, 1.0], [0.01, 0.0, 0.04, 1.0], [0.0, 0.01, 0.04, 1.0]])
    target = np.array([[0.1, 0.1, 0.001, 1.0], [0.3, -0.1, 0.001, 1.0], [0.2, 0.0, 0.001, 1.0]])
    cube_only = {"pointcloud": {"xyzw": blue, "rgb": np.tile([58, 102, 187], (3, 1))}}
    assert eyes({**arm, **cube_only}) is None  # the target is out of sight
    both = {
        "xyzw": np.concatenate([blue, target]),
        "rgb": np.concatenate([np.tile([58, 102, 187], (3, 1)), np.tile([204, 71, 76], (3, 1))]),
    }
    seen = eyes({**arm, "pointcloud": both})
    assert seen is not None
    assert np.allclose(seen["extra"]["goal_pos"], [0.2, 0.0, 0.001])
    assert np.allclose(seen["extra"]["obj_pose"][:3], [0.0, 0.0, 0.02], atol=0.011)
    assert np.allclose(seen["extra"]["tcp_pose"], arm["extra"]["tcp_pose"])
