"""What a Job that ended says of its attempt: the final report, from the Job's conditions, its
pods and, when it succeeded, the result in its evaluators' logs.

The result is read once, at the end, by the process that followed the Job: a log lost with its
pod or node is the cluster's doing (run again, no quota used). A Job the cluster stopped (a pod
evicted, refused by its node, lost) or ran past its deadline is the cluster's too: the deadline
covers the whole plan (`active_deadline_for`), the policy's budget being the evaluator's to
enforce.
"""

from __future__ import annotations

import logging

from kubernetes.client import V1Pod

from evaluator.job import JobOutputError, result_from_logs
from evaluator.limits import KUBERNETES, charged, memory_breach
from evaluator.plan import EvaluationPlan
from evaluator.sources import LOG_TAIL_BYTES
from internal_api.schemas import ErrorCause, FinalReport, State
from worker.kubernetes.client import KubernetesError, KubernetesExecutor, LogLost
from worker.kubernetes.manifest import POLICY, JobSpec
from worker.kubernetes.quota import parse_quantity
from worker.kubernetes.status import STOPPED, JobStatus, pod_view
from worker.outcome import conclusion, ended

log = logging.getLogger(__name__)

POLICY_LOG_LINES = 400
MIB = 1 << 20
CLUSTER = ErrorCause.CLUSTER


def final_report(
    executor: KubernetesExecutor, spec: JobSpec, plan: EvaluationPlan, status: JobStatus
) -> FinalReport:
    """The attempt's final report for its Job that ended (`status`: neither pending nor
    running). Raises `KubernetesError` when the pods cannot be read to say who stopped it."""
    if status.phase == "succeeded":
        return _result(executor, spec, plan)
    if status.phase == "missing":
        return ended(State.ERROR, f"the evaluation's Job {spec.name} disappeared", cause=CLUSTER)
    view = executor.pods(spec.submission_id, spec.attempt)
    disrupted = view.disrupted  # evicted, refused...
    if disrupted is not None:  # ...the cluster's doing, not the policy's
        then = " and it then ran out of time" if status.phase == "deadline_exceeded" else ""
        reason = f"the cluster stopped the evaluation{then}: {disrupted}"
        return ended(State.ERROR, reason, cause=CLUSTER)
    if status.phase == "deadline_exceeded":  # it covers the whole plan (`active_deadline_for`):
        # the cluster ran it too slowly, the policy's budget being the evaluator's to enforce
        reason = f"{STOPPED}its Job ran past its deadline ({status.reason})"
        return ended(State.ERROR, reason, cause=CLUSTER)
    if view.evaluator_memory_killed:  # the service's sizing, never the policy's
        limit = int(parse_quantity(spec.evaluator_resources.memory)) // MIB
        reason = (
            f"{STOPPED}the evaluator ran out of memory (its limit of {limit} MiB: raise "
            "MANIEVAL_EVALUATOR_MEMORY)"
        )
        return ended(State.ERROR, reason, cause=CLUSTER)
    return ended(State.ERROR, f"the evaluator failed ({status.reason})")


def _result(executor: KubernetesExecutor, spec: JobSpec, plan: EvaluationPlan) -> FinalReport:
    try:  # the one read of the logs: the pods listed now, not as the watch last saw them
        pods, logs = executor.result_logs(spec.submission_id, spec.attempt, spec.shards)
        result = result_from_logs(plan, logs)
    except LogLost as exc:  # gone with its pod or node: the cluster's doing
        return ended(State.ERROR, f"the evaluation's log was lost: {exc}", cause=CLUSTER)
    except (KubernetesError, JobOutputError) as exc:
        return ended(State.ERROR, f"the evaluation's result could not be read: {exc}")
    view = pod_view(pods)
    detail = view.policy_ended
    if view.policy_memory_killed:  # named as the sandbox and the container engine name it
        breach = memory_breach(KUBERNETES, int(parse_quantity(spec.policy_resources.memory)) // MIB)
        result, detail = charged(result, breach), breach.detail
    return conclusion(result, log_tail=_policy_log(executor, spec, pods), detail=detail)


def _policy_log(executor: KubernetesExecutor, spec: JobSpec, pods: list[V1Pod]) -> str:
    """The policy container's log tail: an extra that never costs a result."""
    try:
        logs = executor.logs(pods, spec.shards, container=POLICY, tail_lines=POLICY_LOG_LINES)
    except KubernetesError as exc:
        log.warning("Job %s: the policy's side could not be read: %s", spec.name, exc)
        return ""
    text = "\n".join(line.rstrip("\n") for line in logs if line)
    return text[-LOG_TAIL_BYTES:]
