"""PickCubeUnreachable-v1: PickCube-v1 with its goal placed out of the arm's reach, so that no
policy ever succeeds: the deliberately broken task that verification must catch
(docs/verification.md)."""

from typing import Any

import torch
from mani_skill.envs.tasks.tabletop.pick_cube import PickCubeEnv
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose

ENV_ID = "PickCubeUnreachable-v1"
GOAL_HEIGHT = 5.0
"""Metres above the table: the Panda reaches under one."""


@register_env(ENV_ID, max_episode_steps=50)
class PickCubeUnreachableEnv(PickCubeEnv):
    """PickCube's scene and success rule, with the goal five metres up."""

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict[str, Any]) -> None:
        super()._initialize_episode(env_idx, options)
        with torch.device(self.device):
            goal = self.goal_site.pose.p.clone()
            goal[..., 2] = GOAL_HEIGHT
            self.goal_site.set_pose(Pose.create_from_pq(p=goal))
