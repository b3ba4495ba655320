"""A policy that costs nothing to think: isolates the protocol's own cost in the benchmark."""

import numpy as np

from manieval_sdk import Policy, serve


class Zero(Policy):
    def act(self, obs: object) -> np.ndarray:
        return np.zeros(self.spec.action_shape, dtype=np.float32)


if __name__ == "__main__":
    serve(Zero())
