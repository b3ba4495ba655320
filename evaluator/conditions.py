"""Sim-to-real stress conditions: what they change in the environment and in what the policy sees.

All randomness is seeded from the episode's seed, so a condition is as reproducible as the
nominal run.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from evaluator.observation import ObservationKeys
from evaluator.suite import ActionDelay, Condition, LowFreq, ObsNoise

Observation = Any


def map_arrays(obs: Observation, fn: Any) -> Observation:
    """Apply `fn` to every array leaf of a (nested) observation."""
    if isinstance(obs, dict):
        return {key: map_arrays(value, fn) for key, value in obs.items()}
    return fn(obs)


class ConditionRuntime:
    """Applies one condition to an episode: env settings, step limit and observation stream."""

    def __init__(self, condition: Condition, *, keys: ObservationKeys | None = None) -> None:
        self.condition = condition
        self.keys = keys or ObservationKeys(None)
        """The entries of each observation the policy may see; the rest is dropped first."""
        self._params = condition.params
        self._sigma = self._params.sigma if isinstance(self._params, ObsNoise) else 0.0
        self._rng = np.random.default_rng(0)
        self._history: deque[Observation] = deque()

    @property
    def observes_every_step(self) -> bool:
        """Whether every step's observation must pass through `observe`, also where the policy
        is not asked (within a chunk): a delay's history and the noise's stream move on with
        each control step, so what the policy sees at a step does not depend on whether it was
        asked at the steps before."""
        return isinstance(self._params, ActionDelay) or self._sigma > 0

    def env_kwargs(self) -> dict[str, Any]:
        """Extra keyword arguments for gym.make."""
        if isinstance(self._params, LowFreq):
            return {"sim_config": {"control_freq": self._params.control_freq}}
        return {}

    def step_limit(self, max_episode_steps: int, default_control_freq: int) -> int:
        """Steps allowed per episode: the same simulated time when the control rate changes."""
        if isinstance(self._params, LowFreq):
            scaled = max_episode_steps * self._params.control_freq / default_control_freq
            return max(1, math.ceil(scaled))
        return max_episode_steps

    def begin_episode(self, seed: int, first_obs: Observation) -> Observation:
        """Start an episode; returns what the policy sees of the first observation."""
        self._rng = np.random.default_rng([seed, 0x5EED])
        self._history.clear()
        first_obs = self.keys.observation(first_obs)
        if isinstance(self._params, ActionDelay):
            self._history.extend([first_obs] * (self._params.steps + 1))
        return self.observe(first_obs, fresh=False)

    def observe(self, obs: Observation, *, fresh: bool = True) -> Observation:
        """What the policy sees, given the environment's latest observation (`fresh`: not
        seen before, so not yet narrowed to the keys the policy may see)."""
        if fresh:
            obs = self.keys.observation(obs)
        if isinstance(self._params, ActionDelay):
            if fresh:
                self._history.append(obs)
                self._history.popleft()
            obs = self._history[0]
        if self._sigma > 0:
            obs = map_arrays(obs, self._add_noise)
        return obs

    def _add_noise(self, array: np.ndarray) -> np.ndarray:
        if array.dtype.kind != "f":
            return array
        noise = self._rng.normal(0.0, self._sigma, size=array.shape)
        return (array + noise).astype(array.dtype)
