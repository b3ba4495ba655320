"""KeepCubeInRing-v1: the cube starts near the middle of PushCube's target ring; the task is
to keep it there, on the table, within half the ring's radius of its centre."""

from typing import Any

import numpy as np
import torch
from mani_skill.envs.tasks.tabletop.push_cube import PushCubeEnv
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose
from transforms3d.euler import euler2quat

ENV_ID = "KeepCubeInRing-v1"
CUBE_SPREAD = 0.05
"""The cube's xy is uniform in a square of this half side (PushCube's is 0.1)."""
GOAL_OFFSET = 0.03
"""The ring's centre is this far at most from the cube, in x and in y: inside the success zone."""


@register_env(ENV_ID, max_episode_steps=50)
class KeepCubeInRingEnv(PushCubeEnv):
    """PushCube's scene with another initial-state distribution and success rule."""

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict[str, Any]) -> None:
        with torch.device(self.device):
            b = len(env_idx)
            self.table_scene.initialize(env_idx)
            xyz = torch.zeros((b, 3))
            xyz[..., :2] = (torch.rand((b, 2)) * 2 - 1) * CUBE_SPREAD
            xyz[..., 2] = self.cube_half_size
            self.obj.set_pose(Pose.create_from_pq(p=xyz, q=[1, 0, 0, 0]))
            goal = xyz.clone()
            goal[..., :2] += (torch.rand((b, 2)) * 2 - 1) * GOAL_OFFSET
            goal[..., 2] = 1e-3
            self.goal_region.set_pose(Pose.create_from_pq(p=goal, q=euler2quat(0, np.pi / 2, 0)))

    def evaluate(self) -> dict[str, torch.Tensor]:
        distance = torch.linalg.norm(
            self.obj.pose.p[..., :2] - self.goal_region.pose.p[..., :2], axis=1
        )
        on_table = self.obj.pose.p[..., 2] < self.cube_half_size + 5e-3
        return {"success": (distance < self.goal_radius / 2) & on_table}
