"""The class a participant subclasses: a policy maps observations to actions."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

Observation = Any
"""A numpy array, or a dict (possibly nested) of numpy arrays, as the task's obs_mode gives."""


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
    once per control step. Observations carry no batch dimension.

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
        """Return the action for this observation, shaped like `spec.action_low`."""
