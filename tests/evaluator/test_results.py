"""How episodes add up to a task's figures (docs/metrics.md)."""

from __future__ import annotations

import pytest

from evaluator.results import EpisodeResult, EvaluationResult, aggregate_task
from evaluator.runner import failed_episode


def episode(index: int, *, once: bool, at_end: bool | None) -> EpisodeResult:
    return EpisodeResult(
        index=index,
        seed=index,
        success_once=once,
        success_at_end=at_end,
        steps=10,
        episode_return=1.0,
        wall_time_s=0.1,
    )


def test_success_at_end_rate_counts_episodes_that_end_in_success_over_planned_ones():
    episodes = [
        episode(0, once=True, at_end=True),
        episode(1, once=True, at_end=False),
        failed_episode(2, 2, "not_run", "stopped", at_end_measured=True),
    ]
    task = aggregate_task("PickCube-v1", 4, episodes)
    assert task.success_rate == pytest.approx(2 / 4)
    assert task.success_at_end_rate == pytest.approx(1 / 4)


def test_success_at_end_is_null_when_episodes_stop_at_the_first_success():
    episodes = [
        episode(0, once=True, at_end=None),
        failed_episode(1, 1, "policy_error", "boom", at_end_measured=False),
    ]
    assert episodes[1].success_at_end is None
    task = aggregate_task("PickCube-v1", 2, episodes)
    assert task.success_rate == 0.5
    assert task.success_at_end_rate is None


def test_a_failed_episode_did_not_succeed_at_the_end_when_that_is_measured():
    failed = failed_episode(0, 7, "invalid_action", "NaN", at_end_measured=True)
    assert (failed.success_once, failed.success_at_end) == (False, False)


def test_a_result_document_of_schema_1_0_still_reads():
    document = {
        "schema_version": "1.0",
        "suite": {"name": "tiny", "version": 1, "sha256": "0" * 64},
        "phase": "dev",
        "policy": "dir:/p",
        "versions": {
            "manieval": "0",
            "mani_skill": "3.0.1",
            "sapien": "3.0.3",
            "torch": "2",
            "python": "3.11",
        },
        "started_at": "2025-01-01T00:00:00Z",
        "finished_at": "2025-01-01T00:01:00Z",
        "status": "completed",
        "score": 1.0,
        "conditions": [
            {
                "name": "nominal",
                "params": {"kind": "nominal"},
                "score": 1.0,
                "tasks": [
                    {
                        "env_id": "PickCube-v1",
                        "episodes_planned": 1,
                        "successes": 1,
                        "success_rate": 1.0,
                        "ci_low": 0.2,
                        "ci_high": 1.0,
                        "success_at_end_rate": 1.0,
                        "mean_steps": 10,
                        "mean_return": 1.0,
                        "episodes": [episode(0, once=True, at_end=True).model_dump(mode="json")],
                    }
                ],
            }
        ],
    }
    result = EvaluationResult.model_validate(document)
    assert result.conditions[0].tasks[0].episodes[0].success_at_end is True
