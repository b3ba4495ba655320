"""Your ManiEval policy: fill in `act` (and `setup`/`reset` if your policy keeps state).

Run it locally against the benchmark before you submit:

    manieval evaluate --policy . --suite maniskill-core --phase dev --tasks PickCube-v1
"""

from __future__ import annotations

from typing import Any

import numpy as np

from manieval_sdk import Policy, TaskSpec, serve


class MyPolicy(Policy):
    def setup(self, spec: TaskSpec) -> None:
        # Called once per task: load task-specific weights here (this first call may be slow).
        super().setup(spec)

    def reset(self, obs: Any, info: dict[str, Any]) -> None:
        # Called at the start of each episode: clear any per-episode memory here.
        pass

    def act(self, obs: Any) -> np.ndarray:
        # `obs` is what the task's obs_mode gives, without a batch dimension: for "state_dict"
        # a nested dict such as obs["extra"]["tcp_pose"] (shape (7,)). Return an array shaped
        # like self.spec.action_low; values outside [action_low, action_high] are clipped.
        # Randomness: draw from self.rng, e.g. self.rng.normal(size=...). The SDK reseeds it
        # from each episode's first observation, and seeds `random`, numpy's global generator
        # and torch likewise, so an episode gets the same draws on every run and every worker.
        action = np.zeros(self.spec.action_shape, dtype=np.float32)
        action[-1] = 1.0  # keep the gripper open
        return action


if __name__ == "__main__":
    serve(MyPolicy())
