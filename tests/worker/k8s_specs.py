"""Job specs and evaluations of the tiny test suite, for the Kubernetes executor's tests."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from evaluator.job import EvaluationJob
from testkit.k8s_double import EVALUATOR_IMAGE, NAMESPACE, POLICY_IMAGE
from worker.kubernetes.manifest import JobSpec, Resources

TINY_SUITE = Path(__file__).parents[1] / "evaluator" / "tiny_suite.yaml"


def tiny_evaluation(*, seeds: Sequence[int] = (100, 101)) -> EvaluationJob:
    """Two PickCube-v1 episodes of the tiny test suite, nominal condition only."""
    return EvaluationJob(
        suite_yaml=TINY_SUITE.read_text(),
        phase="dev",
        seeds={"PickCube-v1": tuple(seeds)},
        conditions=("nominal",),
    )


def make_spec(
    *,
    submission_id: int = 7,
    attempt: int = 1,
    shards: int = 1,
    gpu: bool = False,
    runtime_class_name: str | None = None,
    namespace: str = NAMESPACE,
    policy_image: str = POLICY_IMAGE,
    evaluation: EvaluationJob | None = None,
    evaluator_resources: Resources | None = None,
    **extra: Any,
) -> JobSpec:
    """A valid JobSpec with small resources; override what a test is about (`extra`: any
    other JobSpec field, such as the node-pool ones)."""
    return JobSpec(
        submission_id=submission_id,
        attempt=attempt,
        namespace=namespace,
        evaluator_image=EVALUATOR_IMAGE,
        policy_image=policy_image,
        evaluation=evaluation or tiny_evaluation(),
        evaluator_resources=evaluator_resources or Resources("2", "4Gi", "2Gi"),
        policy_resources=Resources("500m", "1Gi", "512Mi"),
        gpu=gpu,
        active_deadline_seconds=900,
        ttl_seconds_after_finished=600,
        runtime_class_name=runtime_class_name,
        shards=shards,
        **extra,
    )
