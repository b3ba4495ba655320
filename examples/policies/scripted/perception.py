"""Where the objects are, from what a camera sees: the scripted skills' eyes on the visual track.

The visual track gives no object pose, so the objects are found by their colour in the camera
image and placed in the world by the depth image, back-projected with the camera's intrinsics and
extrinsics (`rgbd`), or read off the point cloud, which ManiSkill gives in world coordinates
(`pointcloud`). Numpy only.

What the tabletop tasks look like (mani-skill 3.0.1): PickCube's cube is pure red and its goal is
hidden from the cameras (it comes as `extra/goal_pos`); PushCube's and PullCube's cube is blue and
their goal is a red and white target lying on the table; StackCube's cubes are red (A) and green
(B). Cubes are 4 cm wide.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

Vec = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]
Observation = Any

CUBE_HALF = 0.02
DEPTH_UNIT = 0.001  # ManiSkill's depth images are int16 millimetres
MIN_POINTS = 3
# The top face: points within this of the highest one (depth comes in whole millimetres).
TOP_FACE_BAND = 0.006
YAW_STEPS = 45  # candidate headings over a quarter turn (a square repeats after it)
# A cube is carried with the hand once the fingers have closed on it near the TCP, and dropped
# from the hand when they close on nothing or open.
HELD_DISTANCE = 0.035
CLOSING_WIDTH = 0.075
EMPTY_WIDTH = 0.015
# While the hand is over a cube it hides part of it: the last clear view is kept meanwhile.
HAND_CLEARANCE_XY = 0.06
HAND_CLEARANCE_Z = 0.12


def pure_red(rgb: Vec) -> Mask:
    """PickCube's and StackCube's red cube (231, 4, 4 lit); the wooden table is far less red."""
    r, g, b = rgb.T
    return (r > 100) & (np.maximum(g, b) < 0.15 * r)


def target_red(rgb: Vec) -> Mask:
    """The red of PushCube's and PullCube's target (204, 71, 76 lit); the table's brown
    (116, 69, 42) has green at more than half its red."""
    r, g, b = rgb.T
    return (r > 120) & (np.maximum(g, b) < 0.46 * r)


def cube_blue(rgb: Vec) -> Mask:
    """PushCube's and PullCube's blue cube (58, 102, 187 lit)."""
    r, g, b = rgb.T
    return (b > 80) & (b > r + 50) & (b > g + 40)


def pure_green(rgb: Vec) -> Mask:
    """StackCube's green cube B (3, 231, 3 lit)."""
    r, g, b = rgb.T
    return (g > 100) & (np.maximum(r, b) < 0.15 * g)


def scene_points(obs: Observation) -> tuple[Vec, Vec]:
    """Every valid point the cameras see, in world coordinates, with its colour."""
    if "pointcloud" in obs:
        cloud = obs["pointcloud"]
        xyzw = np.asarray(cloud["xyzw"], dtype=np.float64)
        valid = xyzw[:, 3] > 0
        return xyzw[valid, :3], np.asarray(cloud["rgb"], dtype=np.float64)[valid]
    points, colours = [], []
    for name, images in obs.get("sensor_data", {}).items():
        if "depth" not in images or "rgb" not in images:
            continue
        camera = obs["sensor_param"][name]
        xyz, valid = back_project(images["depth"], camera["intrinsic_cv"], camera["extrinsic_cv"])
        points.append(xyz[valid])
        colours.append(np.asarray(images["rgb"], dtype=np.float64).reshape(-1, 3)[valid])
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(points), np.concatenate(colours)


def back_project(depth: Any, intrinsic: Any, extrinsic: Any) -> tuple[Vec, Mask]:
    """World coordinates of every pixel of a depth image (OpenCV camera conventions: pixel
    centres at +0.5, `extrinsic` maps world to camera), and which pixels hit something."""
    z = np.asarray(depth, dtype=np.float64).reshape(np.shape(depth)[:2]) * DEPTH_UNIT
    k = np.asarray(intrinsic, dtype=np.float64)
    v, u = np.indices(z.shape, dtype=np.float64) + 0.5
    camera = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=-1)
    pose = np.asarray(extrinsic, dtype=np.float64)
    rotation, translation = pose[:, :3], pose[:, 3]
    world: Vec = (camera.reshape(-1, 3) - translation) @ rotation  # R^T (x - t), row-wise
    return world, z.reshape(-1) > 0


def cube_pose(points: Vec, half: float = CUBE_HALF) -> tuple[Vec, float] | None:
    """Centre and heading (radians, modulo a quarter turn) of a cube seen as `points`.

    The top face is a full square whenever the cube is in view, whatever side the camera looks
    from: its heading is the one that boxes it in most tightly, its centre that box's middle.
    """
    if len(points) < MIN_POINTS:
        return None
    top = float(np.max(points[:, 2]))
    face = points[points[:, 2] > top - TOP_FACE_BAND]
    if len(face) < MIN_POINTS:
        face = points
    xy = face[:, :2]
    best: tuple[float, float, Vec] | None = None
    for yaw in np.linspace(0.0, math.pi / 2, YAW_STEPS, endpoint=False):
        axes = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
        local = xy @ axes.T
        low, high = local.min(axis=0), local.max(axis=0)
        area = float(np.prod(high - low))
        if best is None or area < best[0]:
            best = (area, float(yaw), axes.T @ ((low + high) / 2))
    assert best is not None
    _, yaw, centre_xy = best
    return np.array([centre_xy[0], centre_xy[1], top - half]), yaw


def disc_centre(points: Vec) -> Vec | None:
    """Centre of a flat round target whose outer ring is among `points`: its bounding box's
    middle, which a hand hiding part of the inside does not move."""
    if len(points) < MIN_POINTS:
        return None
    centre: Vec = (points.min(axis=0) + points.max(axis=0)) / 2
    return centre


def yaw_quaternion(yaw: float) -> Vec:
    """(w, x, y, z) quaternion of a turn about the vertical."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


@dataclass
class Hand:
    """What the arm's own state says about the hand: TCP position and finger opening."""

    pos: Vec
    width: float

    @classmethod
    def of(cls, obs: Observation) -> Hand:
        """The hand in an observation (`extra/tcp_pose`, `agent/qpos`)."""
        qpos = np.asarray(obs["agent"]["qpos"], dtype=np.float64)
        tcp = np.asarray(obs["extra"]["tcp_pose"], dtype=np.float64)
        return cls(pos=tcp[:3], width=float(qpos[-2] + qpos[-1]))


class CubeTrack:
    """A cube's pose as last seen clearly; carried along with the hand while held."""

    def __init__(self, colour: Callable[[Vec], Mask], *, grasped: bool, still: bool) -> None:
        self.colour = colour
        self.grasped = grasped  # picked up: carried with the hand once the fingers close on it
        self.still = still  # only moved in the hand: the hand over it hides it, it stays put
        self.pos: Vec | None = None
        self.yaw = 0.0
        self.held_offset: Vec | None = None
        self.lost = False  # let go of: wherever it went, the next view counts, hand or not

    def update(self, points: Vec, colours: Vec, hand: Hand) -> None:
        """Fold in this step's view of the scene."""
        if self.held_offset is not None:
            if EMPTY_WIDTH < hand.width < CLOSING_WIDTH:
                self.pos = hand.pos + self.held_offset
                return
            self.held_offset = None  # closed on nothing, or let go: look again
            self.lost = True
        elif self.grasped and self.pos is not None and EMPTY_WIDTH < hand.width < CLOSING_WIDTH:
            if float(np.linalg.norm(self.pos - hand.pos)) < HELD_DISTANCE:
                self.held_offset = self.pos - hand.pos
                return
        if self.still and not self.lost and self.pos is not None and self._hidden_by(hand):
            return
        seen = cube_pose(points[self.colour(colours)])
        if seen is not None:
            self.pos, self.yaw = seen
            self.lost = False

    def _hidden_by(self, hand: Hand) -> bool:
        assert self.pos is not None
        above = hand.pos - self.pos
        return bool(
            float(np.linalg.norm(above[:2])) < HAND_CLEARANCE_XY
            and -CUBE_HALF < above[2] < HAND_CLEARANCE_Z
        )

    def entry(self) -> Vec | None:
        """Position and (w, x, y, z) orientation, as the state observations' `*_pose` entries
        (None: not seen yet)."""
        if self.pos is None:
            return None
        return np.concatenate([self.pos, yaw_quaternion(self.yaw)])


class TargetTrack:
    """A flat target that does not move: found once, then kept."""

    def __init__(self, colour: Callable[[Vec], Mask]) -> None:
        self.colour = colour
        self.pos: Vec | None = None

    def update(self, points: Vec, colours: Vec, hand: Hand) -> None:
        """Look for the target until it has been found."""
        if self.pos is None:
            low = points[:, 2] < 2 * CUBE_HALF  # lying on the table, not a red cube
            self.pos = disc_centre(points[low & self.colour(colours)])

    def entry(self) -> Vec | None:
        """Its position, as the state observations' `goal_pos` (None: not seen yet)."""
        return self.pos


Track = CubeTrack | TargetTrack
TRACKS: dict[str, Callable[[], dict[str, Track]]] = {
    "PickCube-v1": lambda: {"obj_pose": CubeTrack(pure_red, grasped=True, still=True)},
    "StackCube-v1": lambda: {
        "cubeA_pose": CubeTrack(pure_red, grasped=True, still=True),
        "cubeB_pose": CubeTrack(pure_green, grasped=False, still=True),
    },
    "PushCube-v1": lambda: {
        "obj_pose": CubeTrack(cube_blue, grasped=False, still=False),
        "goal_pos": TargetTrack(target_red),
    },
    "PullCube-v1": lambda: {
        "obj_pose": CubeTrack(cube_blue, grasped=False, still=False),
        "goal_pos": TargetTrack(target_red),
    },
}


class Eyes:
    """Per episode: turns a visual observation into the state entries the skills read."""

    def __init__(self, env_id: str) -> None:
        self.tracks = TRACKS[env_id]() if env_id in TRACKS else {}

    def __call__(self, obs: Observation) -> Observation | None:
        """The observation with the objects' poses (and the goal) added under `extra`; None
        while something has not been seen yet."""
        hand = Hand.of(obs)
        points, colours = scene_points(obs)
        entries = {}
        for key, track in self.tracks.items():
            track.update(points, colours, hand)
            entries[key] = track.entry()
        if any(entry is None for entry in entries.values()):
            return None
        return {**obs, "extra": {**obs["extra"], **entries}}
