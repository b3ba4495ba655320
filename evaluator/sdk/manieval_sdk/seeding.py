"""Randomness that is the same for the same episode wherever and whenever it runs.

The evaluator never tells a policy its seeds (the test phase's are secret), but an episode's first
observation follows from its seed. A generator seeded from a hash of that observation draws the
same numbers for the same episode on any machine, with any number of workers, and whatever ran
before it in the process. `serve` does this before every `reset` (and, from the task's spec,
before every `setup`); docs/protocol.md ("Reproducible randomness") specifies the hash so that a
policy in another language can do the same.
"""

from __future__ import annotations

import hashlib
import random
import sys
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from manieval_sdk.policy import Policy, TaskSpec

# Python's `random`, numpy's global generator and torch get a seed from this child of the
# episode's SeedSequence, so that their streams differ from `Policy.rng`'s.
GLOBALS_SPAWN_KEY = (1,)


class _Hasher(Protocol):
    def update(self, data: bytes, /) -> None: ...


def feed_observation(hasher: _Hasher, obs: Any) -> None:
    """Feed an observation to `hasher` in the canonical form of docs/protocol.md: map keys in
    sorted order, each followed by its value; arrays as dtype, shape and little-endian bytes
    (a 0-d array as shape (1,), as numpy's `ascontiguousarray` makes it)."""
    if isinstance(obs, dict):
        for key in sorted(obs, key=str):
            hasher.update(str(key).encode())
            feed_observation(hasher, obs[key])
        return
    # Not in the bundled tasks' observations, but never an error nor a memory address.
    if isinstance(obs, list | tuple):
        for item in obs:
            feed_observation(hasher, item)
        return
    if isinstance(obs, str | bytes) or obs is None:
        hasher.update(obs.encode() if isinstance(obs, str) else obs or b"")
        return
    array = np.ascontiguousarray(obs)
    if array.dtype.byteorder == ">" or (array.dtype.byteorder == "=" and sys.byteorder == "big"):
        array = array.astype(array.dtype.newbyteorder("<"))
    # dtype and shape go in too, so that equal bytes of another layout do not collide.
    hasher.update(f"{array.dtype.str}{array.shape}".encode())
    hasher.update(array.tobytes())


def episode_seed(obs: Any) -> int:
    """The episode's 64-bit seed: the first 8 bytes (little-endian) of the SHA-256 of its first
    observation in canonical form."""
    hasher = hashlib.sha256()
    feed_observation(hasher, obs)
    return int.from_bytes(hasher.digest()[:8], "little")


def task_seed(spec: TaskSpec) -> int:
    """A 64-bit seed from what identifies a task run: the same in every worker that runs it."""
    fields = (spec.env_id, spec.obs_mode, spec.control_mode, spec.control_freq)
    text = "\0".join(str(field) for field in (*fields, spec.max_episode_steps))
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")


def seed_global_generators(seed: int) -> None:
    """Seed Python's `random`, numpy's global generator and torch (only if already imported)."""
    # Separate words for each: `random` and numpy's global generator are both MT19937 and
    # would draw the very same numbers from the same key.
    words = np.random.SeedSequence(seed, spawn_key=GLOBALS_SPAWN_KEY).generate_state(10)
    random.seed(int.from_bytes(words[:4].tobytes(), "little"))
    np.random.seed(words[4:8])
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.manual_seed(int.from_bytes(words[8:].tobytes(), "little"))


def reseed(policy: Policy, seed: int) -> None:
    """Give `policy` a fresh generator from `seed` and, unless it opted out, seed the globals."""
    policy.rng = np.random.default_rng(seed)
    if policy.seed_globals:
        seed_global_generators(seed)
