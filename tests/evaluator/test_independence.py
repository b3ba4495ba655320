"""Every episode's record depends only on (task, condition, seed, policy).

Not on the episodes that ran before it in the same process or environment, nor on how the
episodes were spread over workers: run alone, in sequence, or sharded over 2 or 3 workers, every
record is the same, byte for byte, timings aside.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import TIMINGS, EvaluationResult
from evaluator.suite import load_suite
from tests.evaluator.conftest import SCRIPTED, run, tiny_plan

# `alone` runs 30 episodes one by one, each in fresh processes: minutes on a busy machine.
pytestmark = [pytest.mark.sim, pytest.mark.long, pytest.mark.timeout(900)]

# On PickCube-v1 with a reused scene, seed 7012 came out differently after 7011 (ManiSkill 3.0.1).
SEEDS = (7011, 7012, 7013)
CONDITIONS = ["nominal", "obs_noise"]
# Long enough for the scripted policy to grasp (contacts are what a scene used to carry over).
STEP_LIMIT = 25

Key = tuple[str, str, int]


def core_plan() -> EvaluationPlan:
    """Every task of the core suite, on SEEDS, under two conditions, with short episodes."""
    plan = build_plan(load_suite("maniskill-core"), "dev", conditions=CONDITIONS, episodes=1)
    runs = tuple(
        run.model_copy(
            update={"seeds": SEEDS, "max_episode_steps": min(run.max_episode_steps, STEP_LIMIT)}
        )
        for run in plan.runs
    )
    return plan.model_copy(update={"runs": runs})


def single_episode_plans(plan: EvaluationPlan) -> Iterator[EvaluationPlan]:
    for run_ in plan.runs:
        for seed in run_.seeds:
            yield plan.model_copy(update={"runs": (run_.model_copy(update={"seeds": (seed,)}),)})


def records(result: EvaluationResult, *, positional: bool = True) -> dict[Key, str]:
    """Each episode's record as canonical JSON, keyed by (condition, task, seed)."""
    assert result.status == "completed", result.abort
    leave_out = TIMINGS if positional else {*TIMINGS, "index"}
    return {
        (c.name, t.env_id, e.seed): json.dumps(e.model_dump(exclude=leave_out), sort_keys=True)
        for c in result.conditions
        for t in c.tasks
        for e in t.episodes
    }


@pytest.fixture(scope="module")
def plan() -> EvaluationPlan:
    return core_plan()


@pytest.fixture(scope="module")
def alone(plan: EvaluationPlan) -> dict[Key, str]:
    """Each episode run on its own: a fresh policy process and a fresh environment."""
    found: dict[Key, str] = {}
    for single in single_episode_plans(plan):
        found |= records(run(single, SCRIPTED), positional=False)
    return found


@pytest.fixture(scope="module")
def in_sequence(plan: EvaluationPlan) -> dict[Key, str]:
    return records(run(plan, SCRIPTED, workers=1))


def test_the_sample_makes_contact_so_carried_over_state_would_show(alone: dict[Key, str]):
    episodes = [json.loads(record) for record in alone.values()]
    assert len(episodes) == 6 * len(CONDITIONS) * len(SEEDS)
    assert all(e["failure"] is None for e in episodes)
    assert sum(e["success_once"] for e in episodes) >= 3


def test_episodes_in_sequence_match_episodes_run_alone(
    alone: dict[Key, str], in_sequence: dict[Key, str]
):
    without_index = {
        key: json.dumps({k: v for k, v in json.loads(r).items() if k != "index"}, sort_keys=True)
        for key, r in in_sequence.items()
    }
    assert without_index == alone


@pytest.mark.parametrize("workers", [2, 3])
def test_sharding_over_workers_changes_no_record(
    plan: EvaluationPlan, in_sequence: dict[Key, str], workers: int
):
    assert records(run(plan, SCRIPTED, workers=workers)) == in_sequence


# A stochastic policy written the naive way: numpy's global generator, never seeded by the policy.
NAIVE_STOCHASTIC = """
import numpy as np
from manieval_sdk import Policy, serve

class Noisy(Policy):
    SEED_GLOBALS

    def act(self, obs):
        return np.random.uniform(self.spec.action_low, self.spec.action_high).astype(np.float32)

serve(Noisy())
"""


def naive_policy(make_policy: Callable[[str], Path], *, sdk_seeds_globals: bool) -> Path:
    setting = "pass" if sdk_seeds_globals else "seed_globals = False"
    return make_policy(NAIVE_STOCHASTIC.replace("SEED_GLOBALS", setting))


def test_a_naive_stochastic_policy_gives_the_same_records_with_1_and_3_workers(
    make_policy: Callable[[str], Path],
):
    # The SDK seeds numpy's global generator from each episode's first observation.
    policy = naive_policy(make_policy, sdk_seeds_globals=True)
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal", "obs_noise"])
    assert records(run(plan, policy, workers=1)) == records(run(plan, policy, workers=3))


def test_without_the_sdks_seeding_the_naive_policy_does_not_even_repeat_itself(
    make_policy: Callable[[str], Path],
):
    policy = naive_policy(make_policy, sdk_seeds_globals=False)
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"])
    assert records(run(plan, policy)) != records(run(plan, policy))
