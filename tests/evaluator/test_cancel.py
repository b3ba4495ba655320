"""A cancel stops the run mid-episode, even while the policy is answering a call."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan
from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.sources import LocalDirectory
from tests.evaluator.conftest import tiny_plan, with_limits

pytestmark = pytest.mark.sim

STILL = """
import numpy as np
from manieval_sdk import Policy, serve

class Still(Policy):
    def act(self, obs):
        return np.zeros(self.spec.action_shape, dtype=np.float32)

serve(Still())
"""

STALLS_ON_THIRD_ACT = """
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


def long_episodes(*, episodes: int = 1, steps: int = 100_000) -> EvaluationPlan:
    """PickCube episodes that run to a step limit far beyond any test's patience."""
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=episodes)
    run = plan.runs[0].model_copy(update={"max_episode_steps": steps})
    plan = plan.model_copy(update={"runs": (run,), "ignore_terminations": True})
    return with_limits(plan, first_call_timeout_s=120.0, call_timeout_s=120.0, budget_s=3600.0)


class CancelAfter:
    """A should_stop that says yes from its `polls`-th call on (a cancel arriving mid-run)."""

    def __init__(self, polls: int) -> None:
        self.polls = polls
        self.calls = 0

    def __call__(self) -> bool:
        self.calls += 1
        return self.calls >= self.polls


def episodes_of(result: EvaluationResult) -> list[EpisodeResult]:
    return [e for c in result.conditions for t in c.tasks for e in t.episodes]


def test_a_cancel_between_steps_stops_a_long_episode(make_policy: Callable[[str], Path]):
    cancel = CancelAfter(polls=300)  # well into the first episode: it is polled every step
    result = evaluate(long_episodes(), LocalDirectory(make_policy(STILL)), should_stop=cancel)
    # The episode would have taken 100,000 steps; it was stopped, not finished, and not charged.
    assert result.abort is None
    [episode] = episodes_of(result)
    assert episode.failure == "not_run"


def test_a_cancel_interrupts_a_call_the_policy_has_not_answered(
    make_policy: Callable[[str], Path],
):
    # Before the hang: a few polls per call and step, and every 0.1 s while the policy starts
    # (a few seconds at most). Then every 0.1 s during the hang in the third act, which only
    # its 120 s call timeout would end: the 300th poll falls well inside it.
    cancel = CancelAfter(polls=300)
    result = evaluate(
        long_episodes(), LocalDirectory(make_policy(STALLS_ON_THIRD_ACT)), should_stop=cancel
    )
    assert result.abort is None  # not policy_timeout: the stop came first
    [episode] = episodes_of(result)
    assert episode.failure == "not_run"


def test_a_cancel_stops_every_worker_mid_run(make_policy: Callable[[str], Path]):
    # Per worker: a 2-step PickCube episode, then a PushCube episode that hangs at its first act.
    plan = long_episodes(episodes=2)
    short, long = tiny_plan(conditions=["nominal"], episodes=2).runs
    plan = plan.model_copy(
        update={
            "runs": (
                short.model_copy(update={"max_episode_steps": 2}),
                long.model_copy(update={"max_episode_steps": 100_000}),
            )
        }
    )
    finished: list[EpisodeResult] = []
    polls_since = 0

    def cancelled() -> bool:  # polled by the parent every 0.1 s
        nonlocal polls_since
        if len(finished) < 2:
            return False
        polls_since += 1
        return polls_since >= 30  # 3 s after both short episodes: the workers are in PushCube

    result = evaluate(
        plan,
        LocalDirectory(make_policy(STALLS_ON_THIRD_ACT)),
        workers=2,
        should_stop=cancelled,
        on_episode=lambda _run, episode: finished.append(episode),
    )
    assert result.abort is None  # not policy_timeout: the stop came first
    pick, push = result.conditions[0].tasks
    assert [e.failure for e in pick.episodes] == [None, None]
    assert [e.failure for e in push.episodes] == ["not_run", "not_run"]
