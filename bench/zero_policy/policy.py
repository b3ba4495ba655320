"""A policy that costs nothing to think: isolates the protocol's own cost in the benchmark."""

import numpy as np

from manieval_sdk import Policy, serve


class Zero(Policy):
    def act(self, obs: object) -> np.ndarray:
        chunk = self.spec.action_chunks.execute  # a chunk of what is executed, where it may
        shape = self.spec.action_shape if chunk == 1 else (chunk, *self.spec.action_shape)
        return np.zeros(shape, dtype=np.float32)


if __name__ == "__main__":
    serve(Zero())
