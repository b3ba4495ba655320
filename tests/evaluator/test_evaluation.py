"""End-to-end evaluations on real ManiSkill environments (CPU PhysX, lavapipe)."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from evaluator.results import EvaluationResult, episode_records
from manieval_sdk import Policy, TaskSpec
from tests.evaluator.conftest import (
    REACTIVE_POLICY,
    REPO,
    SCRIPTED,
    run,
    tiny_plan,
)

pytestmark = [pytest.mark.sim, pytest.mark.long]


def test_two_workers_give_the_same_episode_records_as_one(make_policy: Callable[[str], Path]):
    policy = make_policy(REACTIVE_POLICY)
    plan = tiny_plan()
    one = run(plan, policy, workers=1)
    two = run(plan, policy, workers=2)
    assert one.status == two.status == "completed"
    assert episode_records(one) == episode_records(two)


def test_reruns_give_identical_episode_records(make_policy: Callable[[str], Path]):
    policy = make_policy(REACTIVE_POLICY)
    plan = tiny_plan(conditions=["nominal", "obs_noise"])
    assert episode_records(run(plan, policy)) == episode_records(run(plan, policy))


def test_stress_conditions_change_what_the_policy_experiences(make_policy: Callable[[str], Path]):
    result = run(tiny_plan(tasks=["PickCube-v1"]), make_policy(REACTIVE_POLICY))
    returns = {c.name: [e.episode_return for e in c.tasks[0].episodes] for c in result.conditions}
    assert len({tuple(r) for r in returns.values()}) == len(returns)
    low_freq_steps = {e.steps for e in result.conditions[3].tasks[0].episodes}
    assert low_freq_steps == {3}  # 12 steps at 20 Hz are 3 steps at 5 Hz


def test_result_document_round_trips_through_json(make_policy: Callable[[str], Path]):
    result = run(
        tiny_plan(tasks=["PushCube-v1"], conditions=["nominal"]), make_policy(REACTIVE_POLICY)
    )
    again = EvaluationResult.model_validate_json(result.model_dump_json())
    assert again == result
    assert again.suite.name == "tiny"
    assert again.versions.mani_skill == "3.0.1"
    assert again.versions.sapien == "3.0.3"


def load_policy_class(directory: Path) -> type[Policy]:
    spec = importlib.util.spec_from_file_location(
        f"policy_{directory.name}", directory / "policy.py"
    )
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    classes = [
        v
        for v in vars(module).values()
        if isinstance(v, type) and issubclass(v, Policy) and v is not Policy
    ]
    assert len(classes) == 1
    return classes[0]


def batchless(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: batchless(v) for k, v in value.items()}
    return np.asarray(value.cpu().numpy()[0])


def plain_gym_loop(
    policy: Policy, env_id: str, seeds: list[int], steps: int, *, ignore_terminations: bool
) -> list[tuple[Any, ...]]:
    """The same policy in a plain in-process gymnasium loop, written independently."""
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401

    env = gym.make(
        env_id,
        obs_mode="state_dict",
        control_mode="pd_ee_delta_pose",
        sim_backend="physx_cpu",
        render_backend="sapien_cpu",
        max_episode_steps=steps,
    )
    space = env.unwrapped.single_action_space
    policy.setup(
        TaskSpec(
            env_id=env_id,
            obs_mode="state_dict",
            control_mode="pd_ee_delta_pose",
            control_freq=20,
            max_episode_steps=steps,
            action_low=space.low,
            action_high=space.high,
        )
    )
    records = []
    for seed in seeds:
        # A fresh scene per episode, or PhysX carries state over from the previous one.
        obs, info = env.reset(seed=seed, options={"reconfigure": True})
        policy.reset(batchless(obs), {})
        once, total, count = False, 0.0, 0
        for _ in range(steps):
            action = np.clip(
                np.asarray(policy.act(batchless(obs)), np.float64), space.low, space.high
            )
            obs, reward, terminated, truncated, info = env.step(action.astype(np.float32))
            count += 1
            total += float(reward[0])
            once = once or bool(info["success"][0])
            if not ignore_terminations and (bool(terminated[0]) or bool(truncated[0])):
                break
        at_end = bool(info["success"][0]) if ignore_terminations else None
        records.append((seed, once, at_end, count, total))
    env.close()
    return records


@pytest.mark.parametrize(
    ("policy_name", "ignore_terminations"),
    [("reactive", False), ("scripted", False), ("scripted", True)],
)
def test_evaluator_matches_a_plain_gymnasium_loop(
    make_policy: Callable[[str], Path], policy_name: str, ignore_terminations: bool
):
    directory = make_policy(REACTIVE_POLICY) if policy_name == "reactive" else SCRIPTED
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=4)
    plan = plan.model_copy(update={"ignore_terminations": ignore_terminations})
    if policy_name == "scripted":
        # Long enough to succeed (about 20 steps), short enough to see the end of the episode.
        steps = 40 if ignore_terminations else 100
        plan = plan.model_copy(
            update={"runs": (plan.runs[0].model_copy(update={"max_episode_steps": steps}),)}
        )
    run_ = plan.runs[0]
    result = run(plan, directory)
    got = [
        (e.seed, e.success_once, e.success_at_end, e.steps, e.episode_return)
        for e in result.conditions[0].tasks[0].episodes
    ]
    policy = load_policy_class(directory)()
    expected = plain_gym_loop(
        policy,
        "PickCube-v1",
        list(run_.seeds),
        run_.max_episode_steps,
        ignore_terminations=ignore_terminations,
    )
    assert got == expected
    if policy_name == "scripted":
        assert sum(r[1] for r in got) >= 3
    task = result.conditions[0].tasks[0]
    if ignore_terminations:
        assert {r[3] for r in got} == {run_.max_episode_steps}  # every episode ran to the limit
        assert task.success_at_end_rate is not None
    else:
        assert task.success_at_end_rate is None


def test_the_policy_template_runs_as_shipped():
    result = run(
        tiny_plan(conditions=["nominal"], episodes=1), REPO / "examples" / "policy-template"
    )
    assert result.status == "completed"
    assert all(e.failure is None for c in result.conditions for t in c.tasks for e in t.episodes)
