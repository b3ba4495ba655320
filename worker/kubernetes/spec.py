"""The Job of a claimed attempt, from its evaluation and the worker's settings (pure): the
evaluator runs on the challenge's own image where it names one the workers allow."""

from __future__ import annotations

from evaluator.job import evaluation_job
from internal_api.schemas import Assignment
from worker.kubernetes.manifest import JobSpec, Resources, active_deadline_for, needs_gpu
from worker.settings import WorkerSettings


class EvaluatorImageNotAllowed(ValueError):
    """The challenge names an evaluator image the operator has not let the workers run: the
    configuration's doing (`ErrorCause.CONFIGURATION`), never the participant's."""


def evaluator_image(settings: WorkerSettings, handed: Assignment) -> str:
    """The image the attempt's evaluator runs on: its challenge's own if the workers may run
    it (`MANIEVAL_EVALUATOR_IMAGES`), else the workers' own (ValueError if unusable)."""
    if not settings.evaluator_image:
        raise ValueError("no evaluator image is configured (MANIEVAL_EVALUATOR_IMAGE)")
    wanted = handed.evaluator_image
    if wanted is None:
        return settings.evaluator_image
    if wanted not in settings.allowed_evaluator_images:
        raise EvaluatorImageNotAllowed(
            f"the challenge's evaluator image {wanted} is not one this service's workers may "
            "run: an operator must add it to MANIEVAL_EVALUATOR_IMAGES in the workers' "
            "configuration (docs/deploy.md, Task packages)"
        )
    return wanted


def job_spec(settings: WorkerSettings, handed: Assignment) -> JobSpec:
    """The Job of this attempt, from its evaluation and the worker's settings (ValueError if
    bad)."""
    plan = handed.plan
    return JobSpec(
        submission_id=handed.submission_id,
        attempt=handed.attempt,
        namespace=settings.k8s_namespace,
        evaluator_image=evaluator_image(settings, handed),
        policy_image=handed.image,
        evaluation=evaluation_job(plan, suite_yaml=handed.suite_yaml),
        evaluator_resources=Resources(settings.evaluator_cpu, settings.evaluator_memory, "2Gi"),
        policy_resources=Resources(
            cpu=f"{round(settings.policy_cpus * 1000)}m",
            memory=f"{settings.policy_memory_mib}Mi",
            ephemeral_storage="1Gi",
        ),
        gpu=needs_gpu(plan),
        policy_gpus=plan.policy.gpus,
        active_deadline_seconds=active_deadline_for(plan),
        runtime_class_name=settings.k8s_runtime_class,
        shards=handed.shards,
        node_selector=tuple(sorted(settings.k8s_node_selector.items())),
        tolerations=tuple(tuple(t.items()) for t in settings.k8s_tolerations),
        gpu_node_selector=tuple(sorted(settings.k8s_gpu_node_selector.items())),
        gpu_tolerations=tuple(tuple(t.items()) for t in settings.k8s_gpu_tolerations),
        priority_class_name=settings.k8s_priority_class,
        image_pull_secrets=settings.k8s_image_pull_secrets,
        video_claim=settings.k8s_video_claim,
        videos=handed.plan.videos > 0,
    )
