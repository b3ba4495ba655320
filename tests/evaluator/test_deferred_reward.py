"""A step's reward is computed while the policy thinks about the next action; the sums are
exactly those of computing it at each step, whichever way the policy is called."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from evaluator.conditions import ConditionRuntime
from evaluator.episode import run_episode
from evaluator.results import EpisodeResult
from evaluator.sim import DeferredReward, action_bounds, make_env, reward_value
from evaluator.suite import Condition, Nominal
from tests.evaluator.conftest import tiny_plan

pytestmark = pytest.mark.sim

STEPS = 30


class SeededPolicy:
    """A PolicyChannel whose actions come from a seeded generator; it runs the evaluator's
    `meanwhile` work as a remote channel does, or never, as a channel may."""

    policy_time_s = 0.0

    def __init__(self, *, runs_meanwhile: bool, shape: tuple[int, ...]) -> None:
        self._runs_meanwhile = runs_meanwhile
        self._shape = shape
        self._rng = np.random.default_rng(0)
        self.meanwhile_calls = 0

    def start_task(self, spec: dict[str, Any]) -> None:
        pass

    def reset(self, obs: Any, info: dict[str, Any]) -> None:
        self._rng = np.random.default_rng(0)

    def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
        if self._runs_meanwhile:
            self.meanwhile_calls += 1
            meanwhile()
            meanwhile()  # a second call must not count the step twice
        return {"action": self._rng.uniform(-1, 1, self._shape).astype(np.float32)}


def pick_cube() -> Any:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1)
    return make_env(plan.runs[0], nominal())


@pytest.fixture(scope="module")
def env() -> Any:
    env = pick_cube()
    yield env
    env.close()


def nominal() -> ConditionRuntime:
    return ConditionRuntime(Condition(name="nominal", params=Nominal()))


def episode(env: Any, policy: SeededPolicy) -> EpisodeResult:
    return run_episode(
        env,
        policy,
        nominal(),
        index=0,
        seed=3,
        step_limit=STEPS,
        bounds=action_bounds(env),
        ignore_terminations=True,
    )


def test_make_env_defers_maniskill_rewards(env: Any) -> None:
    env.reset(seed=3)
    _, reward, *_ = env.step(np.zeros(env.unwrapped.single_action_space.shape, np.float32))
    assert isinstance(reward, DeferredReward)
    assert reward_value(reward) == reward_value(reward)  # asking twice: the same state


def test_deferred_rewards_sum_to_the_rewards_computed_at_each_step(env: Any) -> None:
    shape = env.unwrapped.single_action_space.shape
    meanwhile = SeededPolicy(runs_meanwhile=True, shape=shape)
    deferred = episode(env, meanwhile)
    ignored = episode(env, SeededPolicy(runs_meanwhile=False, shape=shape))
    base = env.unwrapped
    deferring = base.get_reward
    del base.get_reward  # back to the task's own: each step computes its reward
    try:
        eager = episode(env, SeededPolicy(runs_meanwhile=False, shape=shape))
        env.reset(seed=3)
        _, reward, *_ = env.step(np.zeros(shape, np.float32))
        assert not isinstance(reward, DeferredReward)
    finally:
        base.get_reward = deferring
    assert meanwhile.meanwhile_calls == STEPS
    assert eager.episode_return != 0.0
    for result in (deferred, ignored):
        assert result.failure is None
        assert result.steps == eager.steps == STEPS
        assert result.episode_return == eager.episode_return  # exactly: same values, same order
        assert result.success_once == eager.success_once
        assert result.success_at_end == eager.success_at_end
