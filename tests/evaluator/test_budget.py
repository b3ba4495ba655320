"""The time budget charges the policy for its own time only, and cuts a call at the budget."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import evaluator.runner
from evaluator.runner import budget_share, make_shards
from tests.evaluator.conftest import run, tiny_plan, with_limits

SLOW_ACTS = """
import time
import numpy as np
from manieval_sdk import Policy, serve

class Slow(Policy):
    def setup(self, spec):
        super().setup(spec)
        time.sleep(SETUP_S)  # set-up is bounded by its own timeout, not charged to the budget
    def act(self, obs):
        time.sleep(ACT_S)
        return np.zeros(self.spec.action_shape, dtype=np.float32)

serve(Slow())
"""


def slow_policy(make_policy: Callable[[str], Path], *, setup_s: float, act_s: float) -> Path:
    return make_policy(SLOW_ACTS.replace("SETUP_S", repr(setup_s)).replace("ACT_S", repr(act_s)))


def test_each_shard_gets_its_share_of_the_budget():
    plan = with_limits(tiny_plan(conditions=["nominal"], episodes=3), budget_s=60.0)
    one, two = make_shards(plan, 2)
    assert (one.episode_count(), two.episode_count()) == (4, 2)
    assert budget_share(plan, one) + budget_share(plan, two) == pytest.approx(60.0)
    assert budget_share(plan, one) == pytest.approx(40.0)
    [whole] = make_shards(plan, 1)
    assert budget_share(plan, whole) == pytest.approx(60.0)


@pytest.mark.sim
def test_the_evaluators_start_up_and_the_policys_set_up_are_not_charged(
    make_policy: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
):
    real_make_env = evaluator.runner.make_env

    def slow_make_env(*args: Any, **kwargs: Any) -> Any:
        time.sleep(3.0)  # an evaluator slow to build its simulator: longer than the budget
        return real_make_env(*args, **kwargs)

    monkeypatch.setattr(evaluator.runner, "make_env", slow_make_env)
    plan = with_limits(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=2), budget_s=2.0
    )
    result = run(plan, slow_policy(make_policy, setup_s=3.0, act_s=0.0))
    assert result.status == "completed", result.abort
    assert result.budget is not None
    assert 0 < result.budget.used_s < 2.0
    episodes = result.conditions[0].tasks[0].episodes
    assert sum(e.policy_time_s for e in episodes) == pytest.approx(result.budget.used_s)


@pytest.mark.sim
def test_a_slow_policy_runs_until_its_own_time_is_used_up(make_policy: Callable[[str], Path]):
    plan = with_limits(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=3), budget_s=2.0
    )
    result = run(plan, slow_policy(make_policy, setup_s=0.0, act_s=0.25))
    assert result.status == "aborted"
    assert result.abort is not None
    assert result.abort.kind == "budget_exhausted"
    assert "during 'act'" in result.abort.reason
    episodes = result.conditions[0].tasks[0].episodes
    assert episodes[0].failure == "budget_exhausted"
    # Each answered act cost at least 0.25 s of the 2 s: at most 8 were answered, but some were.
    answered = sum(e.steps for e in episodes)
    assert 0 < answered <= 8
    assert result.budget is not None
    assert result.budget.used_s >= 2.0


@pytest.mark.sim
def test_a_call_in_progress_is_cut_off_where_the_budget_ends(make_policy: Callable[[str], Path]):
    plan = with_limits(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1),
        budget_s=2.0,
        first_call_timeout_s=120.0,
        call_timeout_s=120.0,
    )
    policy = make_policy(
        """
import time
import numpy as np
from manieval_sdk import Policy, serve

class Stalls(Policy):
    calls = 0
    def act(self, obs):
        Stalls.calls += 1
        if Stalls.calls == 3:
            time.sleep(3600)
        return np.zeros(self.spec.action_shape, dtype=np.float32)

serve(Stalls())
"""
    )
    result = run(plan, policy)
    assert result.abort is not None
    assert result.abort.kind == "budget_exhausted"
    assert result.budget is not None
    # The stalled call ended where the budget did, not at its own 120 s timeout.
    assert 2.0 <= result.budget.used_s < 60.0
