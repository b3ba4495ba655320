"""Uniform random baseline: every action is drawn uniformly inside the task's action bounds."""

from __future__ import annotations

import numpy as np

from manieval_sdk import Observation, Policy, TaskSpec

# Stand-in range for action dimensions the task leaves unbounded.
UNBOUNDED_LOW = -1.0
UNBOUNDED_HIGH = 1.0


class RandomPolicy(Policy):
    """Samples uniformly in [action_low, action_high] from the SDK's per-episode generator.

    `self.rng` is reseeded by the SDK from each episode's first observation, so an episode's
    actions depend only on that episode: not on which episodes ran before it, nor on the worker.
    """

    def setup(self, spec: TaskSpec) -> None:
        """Work out finite sampling bounds for the task."""
        super().setup(spec)
        low = np.asarray(spec.action_low, dtype=np.float64)
        high = np.asarray(spec.action_high, dtype=np.float64)
        self._low = np.where(np.isfinite(low), low, UNBOUNDED_LOW)
        self._high = np.where(np.isfinite(high), high, UNBOUNDED_HIGH)
        self._dtype = np.asarray(spec.action_low).dtype

    def act(self, obs: Observation) -> np.ndarray:
        """A fresh uniform sample within the action bounds."""
        action = self.rng.uniform(self._low, self._high)
        return np.clip(action, self._low, self._high).astype(self._dtype)


if __name__ == "__main__":
    from manieval_sdk import serve

    serve(RandomPolicy())
