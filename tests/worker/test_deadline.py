"""An attempt's wall-clock deadline leaves room for what the evaluator itself does, videos
included: a suite that films its episodes must not time out on rendering, which would be
charged to the participant."""

from __future__ import annotations

import math

import pytest

from evaluator.plan import build_plan
from evaluator.suite import load_suite
from worker.deadline import FRAME_RENDER_S, wall_clock_limit_s
from worker.kubernetes.manifest import active_deadline_for

from ..evaluator.conftest import HERE


def test_recorded_frames_extend_the_deadline() -> None:
    suite = load_suite(HERE / "tiny_suite.yaml")  # 12 steps, 3 episodes a task, 4 conditions
    silent = build_plan(suite, "dev")
    filmed = build_plan(suite, "dev", videos=2)
    nominal_only = filmed.model_copy(update={"video_conditions": ("nominal",)})
    frames = (12 + 1) * FRAME_RENDER_S  # the reset frame, then one a step
    base = wall_clock_limit_s(silent)
    # 2 filmed episodes in each of 2 tasks, under 4 conditions or only under nominal
    assert wall_clock_limit_s(filmed) - base == pytest.approx(2 * 2 * 4 * frames)
    assert wall_clock_limit_s(nominal_only) - base == pytest.approx(2 * 2 * frames)


def test_a_jobs_deadline_is_the_plans_wall_clock_limit_plus_its_start_up() -> None:
    """One rule for every executor: the core suite's Job gets what the docker path allows the
    same plan (its budget and the evaluator's own time), and time to schedule and pull on top,
    not only the policy's budget (8,220 s, when its evaluator alone needs more)."""
    plan = build_plan(load_suite("maniskill-core"), "test", secret=b"s" * 32)
    docker = wall_clock_limit_s(plan)
    assert active_deadline_for(plan, startup_s=60) == math.ceil(docker) + 60
    assert active_deadline_for(plan) >= docker + 900
    assert docker > plan.limits.budget_s * 2  # the evaluator's own share is not small
