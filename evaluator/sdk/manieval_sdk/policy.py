"""The class a participant subclasses: a policy maps observations to actions."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

Observation = Any
"""A numpy array, or a dict (possibly nested) of numpy arrays, as the task's obs_mode gives."""


@dataclass(frozen=True)
class ActionChunks:
    """How many actions `act` may return at once for this task, and how many are executed.

    `execute` actions of a chunk are executed before `act` is called again (fewer if the chunk
    is shorter, or the episode ends); 1 (the default, and what an evaluator of protocol 1 means)
    asks for an action at every step. `max_length` is the longest chunk the evaluator takes on
    the wire; the SDK sends only the first `execute` actions, which never exceeds it.
    """

    max_length: int = 1
    execute: int = 1


@dataclass(frozen=True)
class TaskSpec:
    """What the evaluator tells the policy about the task it is about to be evaluated on."""

    env_id: str
    obs_mode: str
    control_mode: str
    control_freq: int
    max_episode_steps: int
    action_low: np.ndarray
    action_high: np.ndarray
    observation_space: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    action_chunks: ActionChunks = field(default_factory=ActionChunks)
    instruction: str = ""
    """What the task asks, in words (e.g. "Pick up the red cube and move it to the goal."),
    for policies that take a language instruction; empty when the suite gives none."""

    @property
    def action_shape(self) -> tuple[int, ...]:
        """Shape of the action array the policy must return."""
        return tuple(self.action_low.shape)


class Policy(ABC):
    """Subclass and override `act` (and `setup`/`reset` when the policy keeps state).

    The evaluator calls `setup` once per task, `reset` at the start of every episode and `act`
    once per control step, or once per chunk of steps when `act` returns a chunk of actions and
    the task takes chunks (`spec.action_chunks`). Observations carry no batch dimension.

    Randomness is reproducible by default: before every `reset`, `serve` sets `self.rng` to a
    generator seeded from the episode's first observation, and seeds Python's `random`, numpy's
    global generator and torch (when the policy imported it) from the same seed; before every
    `setup` it does the same from the task's spec. An episode then draws the same numbers
    wherever and whenever it runs, whatever ran before it (see `manieval_sdk.seeding`).
    """

    seed_globals: ClassVar[bool] = True
    """False: leave Python's, numpy's and torch's global generators to the policy."""

    rng: np.random.Generator
    """This episode's random generator (this task's, in `setup`)."""

    def setup(self, spec: TaskSpec) -> None:
        """Called when a new task starts; `spec` describes its spaces and limits."""
        self.spec = spec

    def reset(self, obs: Observation, info: dict[str, Any]) -> None:  # noqa: B027 (optional hook)
        """Called at the start of each episode with its first observation."""

    @abstractmethod
    def act(self, obs: Observation) -> np.ndarray:
        """Return the action for this observation, shaped like `spec.action_low`; or a chunk of
        H actions, shaped `(H, *spec.action_shape)`, the first for this observation's step.

        Of a chunk the first `spec.action_chunks.execute` actions are executed, one control step
        each, without calling `act` in between; the rest are dropped. Where the task takes no
        chunks (`execute` is 1) only the first one is, and `act` is called again at the next
        step. Actions are never held back and played later.
        """
