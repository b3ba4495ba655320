"""ManiSkill environments as the evaluator uses them: built from a task run, observed as numpy.

Every reset rebuilds the scene (`reconfiguration_freq=1`): ManiSkill 3 keeps PhysX state (contact
caches, joint accelerations) across a plain `reset(seed)`, so an episode would otherwise depend on
the episodes run before it in the same environment. See docs/metrics.md for the measured cost.
"""

from __future__ import annotations

import gc
from collections.abc import Callable
from typing import Any

import numpy as np

from evaluator.conditions import ConditionRuntime, Observation
from evaluator.plan import TaskRun
from evaluator.provenance import render_backend


def make_env(
    run: TaskRun, runtime: ConditionRuntime, *, render: bool = False, frame_size: int | None = None
) -> Any:
    """Create the gymnasium environment for one task run (one environment, no batching);
    with `render`, its frames are `frame_size` pixels a side (None: the task's own camera's)."""
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the ManiSkill environments)

    camera = {"width": frame_size, "height": frame_size} if render and frame_size else None
    env = gym.make(
        run.env_id,
        num_envs=1,
        obs_mode=run.obs_mode,
        control_mode=run.control_mode,
        sim_backend=run.sim_backend,
        render_backend=render_backend(run.sim_backend),
        render_mode="rgb_array" if render else None,
        **({"human_render_camera_configs": camera} if camera else {}),
        max_episode_steps=run.max_episode_steps * 100,  # the evaluator enforces the real limit
        reconfiguration_freq=1,
        **runtime.env_kwargs(),
    )
    _freeze_long_lived_objects()
    defer_rewards(env)
    return env


class DeferredReward:
    """A step's reward, computed when asked for: the policy never sees rewards, so the episode
    loop computes it while the policy thinks about its next action (`reward_value`). It must be
    asked for before the next step moves the simulator on; the episode loop does so."""

    def __init__(self, compute: Callable[[], Any]) -> None:
        self._compute = compute

    def value(self) -> Any:
        """The reward, as the task computes it (a batch-of-one tensor)."""
        return self._compute()


def defer_rewards(env: Any) -> None:
    """Make `env.step` return a `DeferredReward` instead of computing its reward.

    ManiSkill's own step computes the reward last and only returns it, so the values are the
    same, computed from the same state. A task whose class has its own `step` might use its
    reward there: it is left as it is.
    """
    from mani_skill.envs.sapien_env import BaseEnv

    base = env.unwrapped
    if type(base).step is not BaseEnv.step:
        return
    compute = base.get_reward

    def deferred(*, obs: Any, action: Any, info: dict[str, Any]) -> DeferredReward:
        return DeferredReward(lambda: compute(obs=obs, action=action, info=info))

    base.get_reward = deferred


def reward_value(reward: Any) -> float:
    """A step's reward (deferred or not) as a float."""
    if isinstance(reward, DeferredReward):
        reward = reward.value()
    return float(to_numpy(reward))


_frozen = False


def _freeze_long_lived_objects() -> None:
    """Once per process, after the first environment: exempt what exists from garbage collection.

    Each rebuild of the scene runs a full `gc.collect()` (ManiSkill's `_clear`), which otherwise
    walks every object torch and ManiSkill created at import: most of a rebuild's cost.
    """
    global _frozen
    if not _frozen:
        gc.collect()
        gc.freeze()
        _frozen = True


def default_control_freq(env: Any) -> int:
    """The task's own control frequency, before any condition changed it."""
    return int(env.unwrapped._default_sim_config.control_freq)


def control_freq(env: Any) -> int:
    """The control frequency the environment runs at."""
    return int(env.unwrapped.control_freq)


def to_numpy(value: Any) -> Observation:
    """Torch tensors (batch of one) to numpy arrays without the batch dimension, recursively."""
    if isinstance(value, dict):
        return {str(k): to_numpy(v) for k, v in value.items()}
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    array = np.asarray(value)
    if array.ndim >= 1:
        array = array[0]
    return np.array(array, order="C")  # a copy: the simulator reuses its tensors


def flag(value: Any) -> bool:
    """A batch-of-one boolean tensor as a Python bool."""
    return bool(np.asarray(to_numpy(value)).reshape(-1)[0])


def describe_space(space: Any) -> dict[str, Any]:
    """Shape and dtype of every leaf of a (single-environment) observation space."""
    children = getattr(space, "spaces", None)
    if isinstance(children, dict):
        return {str(key): describe_space(value) for key, value in children.items()}
    return {"shape": list(space.shape), "dtype": str(space.dtype)}


def action_bounds(env: Any) -> tuple[np.ndarray, np.ndarray]:
    """Low and high bounds of the (single-environment) action space."""
    space = env.unwrapped.single_action_space
    return np.asarray(space.low, dtype=np.float32), np.asarray(space.high, dtype=np.float32)
