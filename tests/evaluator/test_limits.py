"""evaluator/limits.py: a limit reads the same whichever platform held the policy to it."""

from __future__ import annotations

import re
from datetime import UTC, datetime

from evaluator.evaluation import build_result
from evaluator.limits import (
    ENGINE,
    KUBERNETES,
    SANDBOX,
    charged,
    memory_breach,
    process_breach,
)
from evaluator.results import Abort
from evaluator.runner import ShardOutcome, failed_episode
from tests.evaluator.conftest import tiny_plan
from worker.containers import exit_detail

STARTED = datetime(2026, 1, 1, tzinfo=UTC)


def test_every_platform_names_a_limit_in_the_same_words():
    details = [memory_breach(by, 256).detail for by in (SANDBOX, ENGINE, KUBERNETES)]
    assert exit_detail(exit_code=137, oom_killed=True, memory_mib=256) in details
    shape = re.compile(r"^(.+) stopped it at its memory limit of 256 MiB$")
    assert [shape.fullmatch(d) is not None for d in details] == [True] * 3
    assert process_breach(ENGINE, 64).detail == (
        "the container engine stopped it at its limit of 64 processes"
    )


def aborted(kind: str = "policy_crashed", reason: str = "the policy disconnected"):
    """A result whose policy broke in episode 1 of 3, as the runner records it."""
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=3)
    abort = Abort(kind=kind, reason=reason)  # type: ignore[arg-type]
    seed = plan.runs[0].seeds[1]
    broke = failed_episode(1, seed, kind, reason, at_end_measured=False)  # type: ignore[arg-type]
    outcome = ShardOutcome(episodes=[(0, broke)], abort=(0, 1, abort))
    return build_result(plan, "image", [outcome], started=STARTED)


def test_a_result_charged_to_a_limit_names_it_in_its_abort_and_the_episode_it_broke_in():
    result = aborted()
    breach = memory_breach(KUBERNETES, 2048)
    after = charged(result, breach)
    assert after.abort is not None
    assert after.abort.kind == "memory_limit"
    assert after.abort.reason == (
        "the policy disconnected (Kubernetes stopped it at its memory limit of 2048 MiB)"
    )
    before = [e.failure for e in result.conditions[0].tasks[0].episodes]
    failures = [e.failure for e in after.conditions[0].tasks[0].episodes]
    assert (before, failures) == (
        ["not_run", "policy_crashed", "not_run"],
        ["not_run", "memory_limit", "not_run"],
    )
    assert after.score == result.score  # the limit changes the words, never the numbers
    assert charged(after, breach) == after  # charged once


def test_a_completed_result_is_never_charged():
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1)
    result = build_result(plan, "image", [ShardOutcome()], started=STARTED)
    assert charged(result, memory_breach(KUBERNETES, 2048)) == result
