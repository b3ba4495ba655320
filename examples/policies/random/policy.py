"""Uniform random baseline: every action is drawn uniformly inside the task's action bounds."""

from __future__ import annotations

import hashlib
from typing import Any, Protocol

import numpy as np

from manieval_sdk import Observation, Policy, TaskSpec

# Stand-in range for action dimensions the task leaves unbounded.
UNBOUNDED_LOW = -1.0
UNBOUNDED_HIGH = 1.0


class _Hasher(Protocol):
    """The part of a hashlib object that `feed_observation` uses."""

    def update(self, data: bytes, /) -> None:
        """Absorb more bytes."""


def feed_observation(hasher: _Hasher, obs: Observation) -> None:
    """Feed an observation's keys and array bytes to `hasher`, dict keys in sorted order."""
    if isinstance(obs, dict):
        for key in sorted(obs, key=str):
            hasher.update(str(key).encode())
            feed_observation(hasher, obs[key])
        return
    arr = np.ascontiguousarray(obs)
    # dtype and shape go in too, so equal bytes of different layout do not collide.
    hasher.update(f"{arr.dtype.str}{arr.shape}".encode())
    hasher.update(arr.tobytes())


def episode_seed(obs: Observation) -> int:
    """Seed derived from an episode's first observation alone."""
    hasher = hashlib.sha256()
    feed_observation(hasher, obs)
    return int.from_bytes(hasher.digest()[:8], "little")


class RandomPolicy(Policy):
    """Samples uniformly in [action_low, action_high]; reseeded from each episode's first obs.

    Seeding from the first observation (not a running generator) makes an episode's actions
    independent of which episodes ran before it in the same process.
    """

    def setup(self, spec: TaskSpec) -> None:
        """Work out finite sampling bounds for the task."""
        super().setup(spec)
        low = np.asarray(spec.action_low, dtype=np.float64)
        high = np.asarray(spec.action_high, dtype=np.float64)
        self._low = np.where(np.isfinite(low), low, UNBOUNDED_LOW)
        self._high = np.where(np.isfinite(high), high, UNBOUNDED_HIGH)
        self._dtype = np.asarray(spec.action_low).dtype
        self._rng = np.random.default_rng(0)

    def reset(self, obs: Observation, info: dict[str, Any]) -> None:
        """Reseed from this episode's first observation."""
        self._rng = np.random.default_rng(episode_seed(obs))

    def act(self, obs: Observation) -> np.ndarray:
        """A fresh uniform sample within the action bounds."""
        action = self._rng.uniform(self._low, self._high)
        return np.clip(action, self._low, self._high).astype(self._dtype)


if __name__ == "__main__":
    from manieval_sdk import serve

    serve(RandomPolicy())
