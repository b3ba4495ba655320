"""Scripted, state-based ManiSkill 3 policy for the Panda under pd_ee_delta_pose control."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from manieval_sdk import Observation, Policy, TaskSpec

# pd_ee_delta_pose turns a normalised action of 1 into a 0.1 m / 0.1 rad step of the TCP target.
POS_SCALE = 0.1
ROT_SCALE = 0.1
# ManiSkill 3.0.1 scales the rotation part by rot_lower (-0.1), which flips its sign.
ROT_SIGN = -1.0
GRIPPER_OPEN = 1.0
GRIPPER_CLOSED = -1.0

# A commanded delta is a PD set-point: at 5 Hz the arm settles on it within the step, at 20 Hz it
# covers well under half of it, so faster control rates get a somewhat higher gain (too high and
# the loop rings, especially with noisy observations).
POS_GAIN = 1.0
ROT_GAIN = 1.0
REFERENCE_FREQ = 5.0
MAX_GAIN_BOOST = 1.5

# Finger joint positions sum to roughly the object's width when something is held.
EMPTY_GRIP_WIDTH = 0.015
CLOSE_SECONDS = 0.25
RELEASE_SECONDS = 0.25

# Weight of the newest sample in the averages behind noise-prone decisions.
EMA_WEIGHT = 0.3

# The only observation and control modes the state machines are written for.
OBS_MODE = "state_dict"
CONTROL_MODE = "pd_ee_delta_pose"

Vec = npt.NDArray[np.float64]


def quat_to_matrix(q: Vec) -> Vec:
    """Rotation matrix of a (w, x, y, z) quaternion, normalised first since obs may be noisy."""
    w, x, y, z = q / max(float(np.linalg.norm(q)), 1e-9)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotvec_of(rot: Vec) -> Vec:
    """Axis-angle vector of a rotation matrix."""
    cos = float(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))
    angle = math.acos(cos)
    skew = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if angle < 1e-6:
        return skew / 2.0
    if math.pi - angle > 1e-3:
        scaled: Vec = skew * (angle / (2.0 * math.sin(angle)))
        return scaled
    # Near a half turn the skew part vanishes; read the axis off the symmetric part instead.
    axis = np.sqrt(np.clip((np.diag(rot) + 1.0) / 2.0, 0.0, None))
    signs = np.sign(skew)
    signs[signs == 0] = 1.0
    flipped: Vec = axis * signs * angle
    return flipped


def axis_angle_matrix(axis: Vec, angle: float) -> Vec:
    """Rotation matrix turning `angle` radians about unit `axis` (Rodrigues)."""
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    rot: Vec = np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)
    return rot


def top_down_rotation(closing_angle: float) -> Vec:
    """Gripper frame pointing straight down with its fingers closing along `closing_angle`."""
    y = np.array([math.cos(closing_angle), math.sin(closing_angle), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    return np.stack([np.cross(y, z), y, z], axis=1)


def leaning_rotation(closing_angle: float, lean: float) -> Vec:
    """Top-down frame tipped by `lean` about the finger axis so the fingers point towards +x."""
    down = top_down_rotation(closing_angle)
    tipped = axis_angle_matrix(down[:, 1], lean) @ down
    if tipped[0, 2] < 0:
        tipped = axis_angle_matrix(down[:, 1], -lean) @ down
    return tipped


def nearest_symmetric_angle(current: float, base: float, period: float) -> float:
    """The angle base + k * period closest to `current`: the smallest wrist turn."""
    return base + round((current - base) / period) * period


def planar_angle(vec: Vec) -> float:
    """Heading of a vector's xy projection."""
    return math.atan2(float(vec[1]), float(vec[0]))


def unit(vec: Vec) -> Vec:
    """Vector scaled to unit length (left as is when it is nearly zero)."""
    norm = float(np.linalg.norm(vec))
    return vec / norm if norm > 1e-9 else vec


class Ema:
    """Exponential moving average of a vector, for decisions that must not flicker with noise."""

    def __init__(self, weight: float = EMA_WEIGHT) -> None:
        self.weight = weight
        self.value: Vec | None = None

    def __call__(self, sample: Vec) -> Vec:
        """Fold in a new sample and return the average."""
        if self.value is None:
            self.value = np.array(sample, dtype=np.float64)
        else:
            self.value = self.value + self.weight * (sample - self.value)
        return self.value


class Robot:
    """Read-only view of the Panda's state in one observation."""

    def __init__(self, obs: Observation) -> None:
        tcp = np.asarray(obs["extra"]["tcp_pose"], dtype=np.float64)
        self.pos: Vec = tcp[:3]
        self.rot: Vec = quat_to_matrix(tcp[3:])
        qpos = np.asarray(obs["agent"]["qpos"], dtype=np.float64)
        self.grip_width = float(qpos[-2] + qpos[-1])

    @property
    def closing_angle(self) -> float:
        """Heading of the finger closing axis (the TCP frame's y axis)."""
        return planar_angle(self.rot[:, 1])


def object_pose(obs: Observation, key: str) -> tuple[Vec, Vec]:
    """Position and rotation matrix of a pose entry of obs["extra"]."""
    pose = np.asarray(obs["extra"][key], dtype=np.float64)
    return pose[:3], quat_to_matrix(pose[3:])


class Controller:
    """Turns Cartesian TCP targets into normalised pd_ee_delta_pose actions."""

    # ManiSkill's IK gives up on some larger steps (awkward wrist poses, edge of the workspace)
    # and then holds the arm where it is, every step alike. When several sizeable commands in a
    # row go nowhere, shrink them; grow them back once the arm moves again.
    stall_window = 4
    min_scale = 0.25

    def __init__(self, control_freq: float) -> None:
        # At higher rates the arm covers only part of a commanded delta per step, so push harder.
        boost = min(max(control_freq / REFERENCE_FREQ, 1.0), MAX_GAIN_BOOST)
        self.pos_gain = POS_GAIN * boost
        self.rot_gain = ROT_GAIN * boost
        self.scale = 1.0
        self.poses: list[tuple[Vec, Vec]] = []
        self.pushes: list[bool] = []

    def observe(self, robot: Robot) -> None:
        """Record the arm's pose and adapt the command scale if it has stopped following."""
        self.poses = [*self.poses[-self.stall_window :], (robot.pos, robot.rot)]
        window = self.pushes[-self.stall_window :]
        if len(window) < self.stall_window or len(self.poses) <= self.stall_window:
            return
        (pos0, rot0), (pos1, rot1) = self.poses[0], self.poses[-1]
        moved = float(np.linalg.norm(pos1 - pos0)) > 0.01
        turned = float(np.linalg.norm(rotvec_of(rot1 @ rot0.T))) > 0.02
        if all(window) and not (moved or turned):
            self.scale = max(self.min_scale, self.scale * 0.5)
            self.pushes = []
        elif moved or turned:
            self.scale = min(1.0, self.scale * 1.05)

    def commit(self, action: Vec) -> None:
        """Remember whether this step's command asked for a sizeable motion."""
        pos_step = float(np.linalg.norm(action[:3])) * POS_SCALE
        rot_step = float(np.linalg.norm(action[3:6])) * ROT_SCALE
        self.pushes.append(pos_step > 0.015 or rot_step > 0.03)

    def action(
        self,
        robot: Robot,
        pos: Vec,
        rot: Vec | None,
        gripper: float,
        max_step: float = math.inf,
    ) -> Vec:
        """Action moving the TCP towards `pos`/`rot` (rot None keeps the orientation)."""
        err = pos - robot.pos
        norm = float(np.linalg.norm(err))
        if norm > max_step:
            err = err * (max_step / norm)
        dpos = np.clip(self.pos_gain * err / POS_SCALE, -1.0, 1.0)
        drot = np.zeros(3)
        if rot is not None:
            drot = ROT_SIGN * self.rot_gain * rotvec_of(rot @ robot.rot.T) / ROT_SCALE
            norm = float(np.linalg.norm(drot))
            if norm > 1.0:
                drot = drot / norm
        return np.concatenate([dpos * self.scale, drot * self.scale, [gripper]])

    def hold(self, gripper: float) -> Vec:
        """Action that keeps the arm still."""
        return np.concatenate([np.zeros(6), [gripper]])


def hover_height(xy_error: float, tolerance: float, ceiling: float) -> float:
    """Extra height while still off target in xy, so fingers clear the object on the way in."""
    return float(np.clip(3.0 * (xy_error - tolerance), 0.0, ceiling))


def steps_for(seconds: float, control_freq: float) -> int:
    """Number of control steps spanning `seconds`."""
    return max(1, math.ceil(seconds * control_freq))


class Skill:
    """Per-episode state machine for one task; subclasses fill in `step`."""

    def __init__(self, spec: TaskSpec) -> None:
        self.spec = spec
        self.ctrl = Controller(spec.control_freq)
        self.phase = "start"
        self.phase_steps = 0

    def goto(self, phase: str) -> None:
        """Switch phase and restart its step counter."""
        self.phase = phase
        self.phase_steps = 0

    def __call__(self, obs: Observation) -> Vec:
        """Advance the phase counter and compute this step's action."""
        robot = Robot(obs)
        self.ctrl.observe(robot)
        action = self.step(obs, robot)
        self.ctrl.commit(action)
        self.phase_steps += 1
        return action

    def step(self, obs: Observation, robot: Robot) -> Vec:
        """This step's action."""
        return self.ctrl.hold(GRIPPER_OPEN)


class PickPlace(Skill):
    """Top-down grasp of a cube, then carry it to a goal or set it down on a goal and let go."""

    cube_half = 0.02
    grasp_depth = 0.004
    # Carrying: stop correcting inside hold_tolerance, resume beyond resume_tolerance.
    hold_tolerance = 0.012
    resume_tolerance = 0.02
    # Placing: travel this far above the drop point, let go this far above it.
    travel_clearance = 0.05
    drop_gap = 0.003

    def __init__(
        self, spec: TaskSpec, obj_key: str, goal: Callable[[Observation], Vec], place: bool
    ) -> None:
        super().__init__(spec)
        self.obj_key = obj_key
        self.goal = goal
        self.place = place
        self.resting = False
        self.offset_ema = Ema()
        self.grip_ema = Ema()
        self.width_ema = Ema()
        self.goto("reach")

    def step(self, obs: Observation, robot: Robot) -> Vec:
        """Run the reach / close / carry (or place / open / retreat) sequence."""
        obj_pos, obj_rot = object_pose(obs, self.obj_key)
        if self.phase == "reach":
            return self.reach(robot, obj_pos, obj_rot)
        if self.phase == "close":
            if self.phase_steps + 1 >= steps_for(CLOSE_SECONDS, self.spec.control_freq):
                self.goto("place" if self.place else "carry")
                self.grip_ema, self.width_ema = Ema(), Ema()
            return self.ctrl.hold(GRIPPER_CLOSED)
        if self.phase in ("carry", "place") and not self.holding(robot, obj_pos):
            self.goto("reach")
            lift = robot.pos + np.array([0.0, 0.0, 0.03])
            return self.ctrl.action(robot, lift, None, GRIPPER_OPEN)
        if self.phase == "carry":
            return self.carry(robot, obj_pos, self.goal(obs))
        if self.phase == "place":
            return self.place_on(robot, obj_pos, self.goal(obs))
        if self.phase == "open":
            if self.phase_steps + 1 >= steps_for(RELEASE_SECONDS, self.spec.control_freq):
                self.goto("retreat")
            return self.ctrl.hold(GRIPPER_OPEN)
        return self.retreat(robot, obj_pos)

    def grasp_rotation(self, robot: Robot, obj_rot: Vec) -> Vec:
        """Top-down orientation whose fingers close on a pair of cube faces."""
        face = planar_angle(obj_rot[:, 0])
        angle = nearest_symmetric_angle(robot.closing_angle, face, math.pi / 2)
        return top_down_rotation(angle)

    def reach(self, robot: Robot, obj_pos: Vec, obj_rot: Vec) -> Vec:
        """Open, line up above the cube and descend onto it."""
        target_rot = self.grasp_rotation(robot, obj_rot)
        xy_err = float(np.linalg.norm(obj_pos[:2] - robot.pos[:2]))
        target = obj_pos.copy()
        target[2] = obj_pos[2] - self.grasp_depth + hover_height(xy_err, 0.01, 0.1)
        if robot.grip_width < 0.07:
            # Fingers still closed from a missed grasp: open before going near the cube.
            target[2] = max(target[2], obj_pos[2] + 0.06)
        aligned = xy_err < 0.012 and abs(robot.pos[2] - target[2]) < 0.008
        yaw_err = float(np.linalg.norm(rotvec_of(target_rot @ robot.rot.T)))
        if aligned and yaw_err < 0.15 and robot.grip_width > 0.07:
            self.goto("close")
            return self.ctrl.hold(GRIPPER_CLOSED)
        return self.ctrl.action(robot, target, target_rot, GRIPPER_OPEN)

    def holding(self, robot: Robot, obj_pos: Vec) -> bool:
        """Whether the cube still sits between the fingers (judged on averaged readings)."""
        near = float(np.linalg.norm(self.grip_ema(obj_pos - robot.pos))) < 0.04
        return near and float(self.width_ema(np.array([robot.grip_width]))[0]) > EMPTY_GRIP_WIDTH

    def carry(self, robot: Robot, obj_pos: Vec, goal: Vec) -> Vec:
        """Bring the held cube to the goal and keep still there (the task wants a static arm)."""
        offset = goal - obj_pos
        # Averaged distance plus hysteresis, so noise does not keep the arm fidgeting at the goal.
        dist = float(np.linalg.norm(self.offset_ema(offset)))
        self.resting = dist < (self.resume_tolerance if self.resting else self.hold_tolerance)
        if self.resting:
            return self.ctrl.hold(GRIPPER_CLOSED)
        return self.ctrl.action(robot, robot.pos + offset, None, GRIPPER_CLOSED)

    def place_on(self, robot: Robot, obj_pos: Vec, goal: Vec) -> Vec:
        """Lift, travel above the drop point, lower the cube onto it and let go."""
        offset = goal - obj_pos
        smooth = self.offset_ema(offset)
        xy_err = float(np.linalg.norm(smooth[:2]))
        if xy_err > 0.012:
            offset[2] += self.travel_clearance
            if offset[2] > 0.015:
                # Still low: rise before moving sideways so the cube clears whatever it passes.
                offset[:2] = 0.0
        else:
            offset[2] += self.drop_gap
            if abs(smooth[2] + self.drop_gap) < 0.007:
                self.goto("open")
                return self.ctrl.hold(GRIPPER_OPEN)
        return self.ctrl.action(robot, robot.pos + offset, None, GRIPPER_CLOSED)

    def retreat(self, robot: Robot, obj_pos: Vec) -> Vec:
        """Lift clear of the released cube, then stay still."""
        target = robot.pos.copy()
        target[2] = obj_pos[2] + 0.07
        if abs(robot.pos[2] - target[2]) < 0.01:
            return self.ctrl.hold(GRIPPER_OPEN)
        return self.ctrl.action(robot, target, None, GRIPPER_OPEN)


class Push(Skill):
    """Slide a cube across the table to a goal with the closed fingers (pushing or pulling)."""

    push_height = 0.02
    contact = 0.035
    standoff = 0.055
    advance = 0.04
    speed = 0.6
    # Success needs the cube within 0.1 m of the goal; stop well inside that.
    done_radius = 0.05
    resume_radius = 0.085
    # Leaning the fingers away from the base buys ~6 cm of reach at table height.
    lean = 0.5

    def __init__(self, spec: TaskSpec) -> None:
        super().__init__(spec)
        self.goto("align")

    def step(self, obs: Observation, robot: Robot) -> Vec:
        """Line up behind the cube (seen from the goal), then drive it to the goal."""
        obj_pos, _ = object_pose(obs, "obj_pose")
        goal = np.asarray(obs["extra"]["goal_pos"], dtype=np.float64)
        to_goal = goal[:2] - obj_pos[:2]
        dist = float(np.linalg.norm(to_goal))
        direction = unit(to_goal)
        rot = leaning_rotation(robot.closing_angle, self.lean)
        if self.phase == "done" and dist < self.resume_radius:
            return self.ctrl.hold(GRIPPER_CLOSED)
        if dist < self.done_radius:
            # Stop at once: chasing a sliding cube only knocks it further.
            self.goto("done")
            return self.ctrl.hold(GRIPPER_CLOSED)
        if self.phase != "push":
            return self.align(robot, obj_pos, direction, rot)
        return self.push(robot, obj_pos, direction, dist, rot)

    def align(self, robot: Robot, obj_pos: Vec, direction: Vec, rot: Vec) -> Vec:
        """Come down onto the table a little behind the cube."""
        self.phase = "align"
        target = np.empty(3)
        target[:2] = obj_pos[:2] - direction * self.standoff
        xy_err = float(np.linalg.norm(target[:2] - robot.pos[:2]))
        target[2] = self.push_height + hover_height(xy_err, 0.01, 0.1)
        if xy_err > 0.02 and robot.pos[2] < self.push_height + 0.03:
            # Down at cube level: rise before moving sideways, or the fingers sweep the cube.
            target[:2] = robot.pos[:2]
        if xy_err < 0.015 and abs(robot.pos[2] - self.push_height) < 0.01:
            self.goto("push")
        return self.ctrl.action(robot, target, rot, GRIPPER_CLOSED)

    def push(self, robot: Robot, obj_pos: Vec, direction: Vec, dist: float, rot: Vec) -> Vec:
        """Track a point just behind the cube that runs ahead towards the goal."""
        behind = obj_pos[:2] - direction * self.contact
        if float(np.linalg.norm(behind - robot.pos[:2])) > 0.05:
            # Lost contact (cube slid sideways): go round and line up again.
            self.goto("align")
        target = np.empty(3)
        target[:2] = behind + direction * min(self.advance, dist)
        target[2] = self.push_height
        max_step = self.speed / self.spec.control_freq
        return self.ctrl.action(robot, target, rot, GRIPPER_CLOSED, max_step=max_step)


class LiftPegUpright(Skill):
    """Grasp a lying peg near one end, lift, turn it upright about the finger axis, set it down."""

    peg_half_length = 0.12
    # Holding the peg off-centre keeps the TCP high once the peg stands, where the arm can still
    # point the fingers sideways.
    grasp_offset = 0.08
    turn_height = 0.23
    turn_x = -0.2
    stand_height = 0.121
    upright_tolerance = 0.05

    def __init__(self, spec: TaskSpec) -> None:
        super().__init__(spec)
        self.grasp_rot: Vec | None = None
        self.goto("reach")

    def step(self, obs: Observation, robot: Robot) -> Vec:
        """Run the reach / close / lift / turn / lower sequence."""
        peg_pos, peg_rot = object_pose(obs, "obj_pose")
        if self.phase == "reach":
            return self.reach(robot, peg_pos, peg_rot)
        if self.phase == "close":
            if self.phase_steps + 1 >= steps_for(CLOSE_SECONDS, self.spec.control_freq):
                self.goto("lift")
                self.grasp_rot = robot.rot.copy()
            return self.ctrl.hold(GRIPPER_CLOSED)
        return self.swing(robot, peg_pos, peg_rot)

    def grasp_point(self, peg_pos: Vec, peg_rot: Vec) -> Vec:
        """Point on the peg's axis towards the base (-x); that end ends up on top."""
        axis = peg_rot[:, 0] if peg_rot[0, 0] > 0 else -peg_rot[:, 0]
        return peg_pos - axis * self.grasp_offset

    def reach(self, robot: Robot, peg_pos: Vec, peg_rot: Vec) -> Vec:
        """Open, line up over the grasp point with fingers across the peg, and descend."""
        across = planar_angle(peg_rot[:, 0]) + math.pi / 2
        target_rot = top_down_rotation(
            nearest_symmetric_angle(robot.closing_angle, across, math.pi)
        )
        target = self.grasp_point(peg_pos, peg_rot)
        xy_err = float(np.linalg.norm(target[:2] - robot.pos[:2]))
        target[2] += hover_height(xy_err, 0.01, 0.1)
        aligned = xy_err < 0.012 and abs(robot.pos[2] - target[2]) < 0.008
        yaw_err = float(np.linalg.norm(rotvec_of(target_rot @ robot.rot.T)))
        if aligned and yaw_err < 0.1:
            self.goto("close")
            return self.ctrl.hold(GRIPPER_CLOSED)
        return self.ctrl.action(robot, target, target_rot, GRIPPER_OPEN)

    def swing(self, robot: Robot, peg_pos: Vec, peg_rot: Vec) -> Vec:
        """Lift clear, turn the peg upright, then lower it onto its end."""
        tilt = math.acos(min(1.0, abs(float(peg_rot[2, 0]))))
        target = robot.pos.copy()
        if self.phase == "lift":
            # With the fingers pointing back at the base the wrist sits ~0.2 m further out than
            # the TCP, so bring the TCP in towards the base before turning.
            target[0] = self.turn_x
            target[2] = self.turn_height
            if float(np.linalg.norm(target - robot.pos)) < 0.02:
                self.goto("turn")
            return self.ctrl.action(robot, target, None, GRIPPER_CLOSED)
        if self.phase == "turn":
            if tilt < self.upright_tolerance:
                self.goto("lower")
            # Keep lifting against the sag of the loaded arm so the lower end clears the table.
            target[2] = self.turn_height
            return self.ctrl.action(robot, target, self.upright_rotation(), GRIPPER_CLOSED)
        # The peg slips a little in the fingers, so level the peg itself rather than the hand.
        target[2] += self.stand_height - peg_pos[2]
        level = self.levelling_rotation(robot, peg_rot)
        return self.ctrl.action(robot, target, level, GRIPPER_CLOSED)

    def levelling_rotation(self, robot: Robot, peg_rot: Vec) -> Vec:
        """Hand orientation that would bring the peg's long axis exactly vertical."""
        axis = peg_rot[:, 0] if peg_rot[2, 0] > 0 else -peg_rot[:, 0]
        up = np.array([0.0, 0.0, 1.0])
        turn = np.cross(axis, up)
        sin = float(np.linalg.norm(turn))
        if sin < 1e-6:
            return robot.rot
        return axis_angle_matrix(turn, math.atan2(sin, float(axis @ up))) @ robot.rot

    def upright_rotation(self) -> Vec:
        """Grasp orientation turned a quarter turn about the finger axis."""
        assert self.grasp_rot is not None
        closing = self.grasp_rot[:, 1]
        # Turn so the fingers end up pointing back at the base (-x): the other way runs the
        # wrist (joint 6) into its limit.
        turned = axis_angle_matrix(closing, math.pi / 2) @ self.grasp_rot
        if turned[0, 2] > 0:
            turned = axis_angle_matrix(closing, -math.pi / 2) @ self.grasp_rot
        return turned


def stack_goal(obs: Observation) -> Vec:
    """Where cube A's centre goes: resting on top of cube B."""
    cube_b: Vec = np.asarray(obs["extra"]["cubeB_pose"], dtype=np.float64)[:3]
    goal: Vec = cube_b + np.array([0.0, 0.0, 2 * PickPlace.cube_half])
    return goal


def pick_goal(obs: Observation) -> Vec:
    """PickCube's goal position."""
    return np.asarray(obs["extra"]["goal_pos"], dtype=np.float64)


SKILLS: dict[str, Callable[[TaskSpec], Skill]] = {
    "PickCube-v1": lambda spec: PickPlace(spec, "obj_pose", pick_goal, place=False),
    "StackCube-v1": lambda spec: PickPlace(spec, "cubeA_pose", stack_goal, place=True),
    "PushCube-v1": Push,
    "PullCube-v1": Push,
    "LiftPegUpright-v1": LiftPegUpright,
}


class ScriptedPolicy(Policy):
    """Hand-written state machines per task; a still, open gripper for unknown tasks."""

    def setup(self, spec: TaskSpec) -> None:
        """Remember the task and pick its state machine (and its eyes, on the visual track)."""
        super().setup(spec)
        self._make_eyes: Callable[[str], Callable[[Observation], Observation | None]] | None = None
        supported = spec.control_mode == CONTROL_MODE
        if spec.obs_mode != OBS_MODE:
            # No object poses: find the objects in the camera's view (perception.py). Imported
            # here, so that this file alone still runs on the state track.
            from perception import TRACKS, Eyes

            supported = supported and spec.env_id in TRACKS
            self._make_eyes = Eyes
        self._make_skill = SKILLS.get(spec.env_id) if supported else None
        self._skill: Skill | None = None
        self._eyes: Callable[[Observation], Observation | None] | None = None

    def reset(self, obs: Observation, info: dict[str, Any]) -> None:
        """Start a fresh state machine for the new episode."""
        self._skill = self._make_skill(self.spec) if self._make_skill else None
        self._eyes = self._make_eyes(self.spec.env_id) if self._make_eyes else None

    def act(self, obs: Observation) -> np.ndarray:
        """Next action, clipped to the action bounds."""
        low, high = self.spec.action_low, self.spec.action_high
        if self._skill is None or low.shape != (7,):
            return self.safe_action()
        if self._eyes is not None:
            obs = self._eyes(obs)
            if obs is None:  # an object out of sight, and never seen: wait for a view
                return self.safe_action()
        action = self._skill(obs)
        return np.clip(action, low, high).astype(low.dtype)

    def safe_action(self) -> np.ndarray:
        """Zero motion with the gripper (assumed to be the last entry) open."""
        low, high = self.spec.action_low, self.spec.action_high
        action = np.clip(np.zeros(low.shape, dtype=low.dtype), low, high)
        if action.size:
            action.reshape(-1)[-1] = high.reshape(-1)[-1]
        return action


if __name__ == "__main__":
    from manieval_sdk import serve

    serve(ScriptedPolicy())
