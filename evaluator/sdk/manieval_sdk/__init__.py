"""ManiEval participant SDK: subclass `Policy`, then call `serve(policy)`.

Depends on numpy and msgpack only, so it fits in any policy image.
"""

from manieval_sdk.policy import ActionChunks, Observation, Policy, TaskSpec
from manieval_sdk.seeding import episode_seed
from manieval_sdk.serve import serve

__all__ = ["ActionChunks", "Observation", "Policy", "TaskSpec", "episode_seed", "serve"]
