"""What Job, pod and event objects say, read into the executor's view (pure, no I/O).

`job_status` reads a Job's conditions, `job_ref` a listed Job's attempt, and `pod_view` an
attempt's pods: a container that cannot start (a bad image name, say) or whose image the kubelet
is still trying to pull, how the policy container last ended, and whether the cluster (not the
evaluation) evicted, preempted, lost, refused at its node or could not schedule a pod, so the
worker can give every run a reason; `pending_verdict` says whose doing pods that never started
are. `pods_by_index` picks the pod whose log stands for each shard, and `warnings` reads the
cluster's warnings about a Job.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any, Literal

from kubernetes.client import V1Job, V1Pod

from evaluator.plan import EvaluationPlan
from internal_api.schemas import ErrorCause
from worker.kubernetes.manifest import (
    ATTEMPT_LABEL,
    EVALUATOR,
    INDEX_LABEL,
    POLICY,
    SUBMISSION_LABEL,
)

Phase = Literal["pending", "running", "succeeded", "failed", "deadline_exceeded", "missing"]


@dataclass(frozen=True)
class JobStatus:
    """Where a Job is, from its conditions; `reason` says why it failed."""

    phase: Phase
    reason: str = ""
    disrupted: str | None = None
    """How a pod disruption failed the Job (its podFailurePolicy's FailJob rule on
    DisruptionTarget): the Job's own record, there when the evicted pod is long gone."""


@dataclass(frozen=True)
class JobRef:
    """A Job of ours as listed: which attempt it runs and where it is."""

    name: str
    submission_id: int
    attempt: int
    status: JobStatus
    terminating: bool
    created: datetime | None = None


@dataclass(frozen=True)
class PullFailure:
    """A container whose image the kubelet could not pull yet, and what it says."""

    container: str
    detail: str

    def __str__(self) -> str:
        return f"the {self.container} container: {self.detail}"


STOPPED = "the cluster stopped the evaluation: "


@dataclass(frozen=True)
class Verdict:
    """Why an attempt ends `error` while its Job runs on, and who caused it: the cluster (the
    attempt runs again, no quota used) or None (an error to look at, not run again)."""

    reason: str
    cause: ErrorCause | None = ErrorCause.CLUSTER


@dataclass(frozen=True)
class PodView:
    """What an attempt's pods say beyond the Job's conditions."""

    stuck: str | None = None
    """A container that cannot start whatever the wait (a bad image name, say), and why."""
    pulling: PullFailure | None = None
    """A container whose image pull failed: the kubelet tries again, with back-off."""
    policy_ended: str | None = None
    """How the policy container last ended, when it did not exit cleanly (OOMKilled, a code)."""
    policy_memory_killed: bool = False
    """Whether that end was the kubelet killing it at its memory limit (`OOMKilled`)."""
    evaluator_memory_killed: bool = False
    """Whether an evaluator container was killed at its memory limit: the service's sizing."""
    evaluating: bool = False
    """Whether an evaluator container has started in some pod."""
    started: int = 0
    """In how many pods the evaluator container has started (an Indexed Job has one per
    shard: one shard left unscheduled holds the whole result)."""
    disrupted: str | None = None
    """How the cluster evicted, preempted, lost or refused a pod of the Job (a DisruptionTarget
    condition, a pod failed with a reason of the kubelet's such as Evicted or NodeLost, or
    refused by its node's kubelet at admission, such as OutOfcpu)."""
    unschedulable: str | None = None
    """Why the scheduler cannot place a pending pod (PodScheduled=False, Unschedulable)."""
    alive: frozenset[str] = frozenset()
    """The pods not yet ended (neither Succeeded nor Failed), by name."""
    names: frozenset[str] = frozenset()
    """Every pod of the Job listed, ended or not."""

    @property
    def count(self) -> int:
        """How many pods the Job has at all."""
        return len(self.names)


def job_status(job: V1Job) -> JobStatus:
    """A Job's phase from its conditions and its ready pods.

    The Job controller decides a Job's end before it says so: from Kubernetes 1.31 it writes
    SuccessCriteriaMet or FailureTarget, ends the pods still running, and adds Complete or
    Failed (same reason) only once none is left terminating (`delayTerminalCondition` in
    pkg/controller/job/job_controller.go). The first condition is the decision: the pods'
    deletion that follows it is the Job's end, not the cluster's doing."""
    status = job.status
    true = {c.type: c for c in (status.conditions or []) if c.status == "True"} if status else {}
    if "Complete" in true or "SuccessCriteriaMet" in true:
        return JobStatus("succeeded")
    failed = true.get("Failed") or true.get("FailureTarget")
    if failed is not None:
        reason = f"{failed.reason or 'Failed'}: {failed.message or ''}".rstrip(": ")
        phase: Phase = "deadline_exceeded" if failed.reason == "DeadlineExceeded" else "failed"
        return JobStatus(phase, reason, disrupted=_job_disruption(failed))
    if status is not None and (status.ready or 0) > 0:
        return JobStatus("running")
    return JobStatus("pending")


DISRUPTION_RULE = re.compile(
    r"^Pod [^/\s]+/(?P<pod>\S+) has condition DisruptionTarget matching FailJob rule at index \d+$"
)
"""The message of a Job failed by a FailJob rule on a pod condition, DisruptionTarget here:
`matchPodFailurePolicy` in pkg/controller/job/pod_failure_policy.go writes
"Pod %s/%s has condition %v matching %v rule at index %d" (namespace, pod, the condition's
type, the action, the rule's index), under the reason PodFailurePolicy
(`batch.JobReasonPodFailurePolicy`), on FailureTarget then Failed."""


def _job_disruption(failed: Any) -> str | None:
    """How a pod disruption failed the Job, read from its failure condition alone."""
    match = DISRUPTION_RULE.match(failed.message or "")
    if failed.reason != "PodFailurePolicy" or match is None:
        return None
    why = f"{failed.reason}: {failed.message}"
    return f"pod {match['pod']} was disrupted by the cluster, which failed its Job ({why})"


def job_ref(job: V1Job) -> JobRef | None:
    """A listed Job's attempt and status; None for a Job without our labels."""
    meta = job.metadata
    labels = (meta.labels if meta else None) or {}
    submission, attempt = labels.get(SUBMISSION_LABEL, ""), labels.get(ATTEMPT_LABEL, "")
    if meta is None or not meta.name or not submission.isdigit() or not attempt.isdigit():
        return None  # not one we made: never touch it
    return JobRef(
        name=meta.name,
        submission_id=int(submission),
        attempt=int(attempt),
        status=job_status(job),
        terminating=meta.deletion_timestamp is not None,
        created=meta.creation_timestamp,
    )


def pods_by_index(pods: Iterable[V1Pod]) -> dict[int, V1Pod]:
    """The pod whose log stands for each shard index."""
    chosen: dict[int, V1Pod] = {}
    for pod in pods:
        index = _pod_index(pod)
        if index not in chosen or _preference(pod) > _preference(chosen[index]):
            chosen[index] = pod
    return chosen


def pod_view(pods: list[V1Pod], *, job: JobStatus | None = None) -> PodView:
    """What an attempt's pods say: a container that cannot start, how the policy ended. A
    disruption the `job` recorded counts when no pod says it (its pods deleted since)."""
    view = PodView(names=frozenset((p.metadata.name or "") for p in pods if p.metadata))
    for pod in pods:
        status = pod.status
        if status is None:
            continue
        name = pod.metadata.name if pod.metadata and pod.metadata.name else ""
        if status.phase not in ("Succeeded", "Failed"):
            view = replace(view, alive=view.alive | {name})
        if view.disrupted is None:
            view = replace(view, disrupted=_disruption(name, status))
        if view.unschedulable is None:
            view = replace(view, unschedulable=_unschedulable(status))
        before = view.evaluating
        view = replace(view, evaluating=False)
        containers = [*(status.init_container_statuses or []), *(status.container_statuses or [])]
        evaluator_end = _evaluator_end(containers)
        for container in containers:
            view = _look(view, container, evaluator_end)
        started = view.evaluating
        view = replace(view, evaluating=before or started, started=view.started + started)
    if view.disrupted is None and job is not None:
        view = replace(view, disrupted=job.disrupted)
    return view


def warnings(events: Iterable[Any]) -> list[str]:
    """The Warning events among `events`, oldest first, as `Reason: message`."""
    found = [e for e in events if e.type == "Warning"]
    found.sort(key=_event_time)
    return [f"{e.reason or 'Warning'}: {e.message or ''}".rstrip(": ") for e in found]


def _pod_index(pod: V1Pod) -> int:
    meta = pod.metadata
    value = ((meta.labels or {}).get(INDEX_LABEL) if meta else None) or (
        (meta.annotations or {}).get(INDEX_LABEL) if meta else None
    )
    return int(value) if value is not None and value.isdigit() else 0


def _preference(pod: V1Pod) -> tuple[bool, float]:
    """A succeeded pod's log first, else the newest pod's."""
    phase = pod.status.phase if pod.status else None
    created = pod.metadata.creation_timestamp if pod.metadata else None
    return (phase == "Succeeded", created.timestamp() if created else 0.0)


STUCK_REASONS = frozenset(
    {"InvalidImageName", "ErrImageNeverPull", "CreateContainerConfigError", "CreateContainerError"}
)
"""Waiting reasons that do not resolve by waiting."""
PULL_REASONS = frozenset({"ErrImagePull", "ImagePullBackOff", "RegistryUnavailable"})
"""Waiting reasons of a failed pull the kubelet tries again, each time after a longer back-off
(10 s doubling to 300 s: `imageBackOff` in pkg/kubelet/kubelet.go; ErrImagePull, then
ImagePullBackOff while it waits: `EnsureImageExists` in pkg/kubelet/images/image_manager.go).
A registry restarting or a node's network recovers; the wait is bounded by the pending timeout."""


def _evaluator_end(containers: list[Any]) -> datetime | None:
    """When the pod's evaluator container ended, if it has (datetime.max: it did, untimed)."""
    for container in containers:
        state = container.state
        if container.name == EVALUATOR and state is not None and state.terminated is not None:
            return state.terminated.finished_at or datetime.max.replace(tzinfo=UTC)
    return None


def _look(view: PodView, container: Any, evaluator_end: datetime | None) -> PodView:
    state, last = container.state, container.last_state
    waiting = state.waiting if state is not None else None
    if waiting is not None and waiting.reason in STUCK_REASONS | PULL_REASONS:
        detail = f"{waiting.reason}: {waiting.message}" if waiting.message else waiting.reason
        if view.stuck is None and waiting.reason in STUCK_REASONS:
            view = replace(view, stuck=f"the {container.name} container: {detail}")
        elif view.pulling is None and waiting.reason in PULL_REASONS:
            view = replace(view, pulling=PullFailure(container.name, detail))
    if container.name == EVALUATOR and state is not None and (state.running or state.terminated):
        view = replace(view, evaluating=True)
        for ended in (state.terminated, last.terminated if last is not None else None):
            if ended is not None and ended.reason == "OOMKilled":
                view = replace(view, evaluator_memory_killed=True)
    if container.name == POLICY and view.policy_ended is None:
        # Its last state first: a crash or OOM kill the sidecar was restarted after. An end at
        # or after the evaluator's is the kubelet stopping the sidecar (SIGTERM, then a kill
        # after the grace period: exit 137 from a PID 1 that ignores SIGTERM): not the policy's.
        # A restart is never the kubelet's stop: the last state always counts.
        current = state.terminated if state is not None else None
        if current is not None and _stopped_after(current, evaluator_end):
            current = None
        for ended in (last.terminated if last is not None else None, current):
            if ended is not None and (ended.reason == "OOMKilled" or ended.exit_code):
                killed = ended.reason == "OOMKilled"
                view = replace(view, policy_ended=_ending(ended), policy_memory_killed=killed)
                break
    return view


def _stopped_after(ended: Any, evaluator_end: datetime | None) -> bool:
    """Whether a sidecar's end came once the evaluator had ended (the kubelet's stop)."""
    if evaluator_end is None:
        return False
    return ended.finished_at is None or ended.finished_at >= evaluator_end


DISRUPTING_REASONS = frozenset(
    {"Evicted", "NodeLost", "Preempting", "Shutdown", "Terminated", "NodeShutdown"}
)
"""Reasons a pod fails for that are the node's or the cluster's doing, never the evaluation's."""
ADMISSION_REASONS = frozenset(
    {
        "UnexpectedAdmissionError",
        "UnexpectedPredicateFailureType",
        "UnknownReason",
        "InvalidNodeInfo",
        "NodeAffinity",
        "TaintToleration",
    }
)
"""Reasons the kubelet refuses a pod the scheduler placed on its node (pkg/kubelet/lifecycle/
predicate.go): the node's view of its room or labels differs from the scheduler's, or a device
plugin's allocation failed (UnexpectedAdmissionError). `OutOf<resource>` (OutOfcpu,
OutOfmemory, OutOfnvidia.com/gpu) says which resource it found short. The pod fails at once,
never having run: the node's doing, never the evaluation's."""


def _disruption(name: str, status: Any) -> str | None:
    for condition in status.conditions or []:
        if condition.type == "DisruptionTarget" and condition.status == "True":
            why = condition.reason or "DisruptionTarget"
            detail = f": {condition.message}" if condition.message else ""
            return f"pod {name} was disrupted by the cluster ({why}{detail})"
    detail = f": {status.message}" if status.message else ""
    if status.phase == "Failed" and status.reason in DISRUPTING_REASONS:
        return f"pod {name} failed on its node ({status.reason}{detail})"
    reason = status.reason or ""
    if status.phase == "Failed" and (reason in ADMISSION_REASONS or reason.startswith("OutOf")):
        return f"pod {name} was refused by its node's kubelet ({reason}{detail})"
    return None


def pending_verdict(view: PodView, waited: float, warning: Callable[[], str]) -> Verdict:
    """Why pods not all started after `waited` seconds (the pending timeout) end the attempt.
    An image still not pulled is the participant's to fix when it is their policy's (the
    registry took it, so it is theirs that does not pull), the cluster's when it is the
    platform's evaluator; `warning` (a request: asked only here) tells the Job's last
    warning, `: reason` or ""."""
    pull = view.pulling
    if pull is not None and pull.container == POLICY:
        return Verdict(f"the evaluation could not start: {pull}", cause=None)
    if pull is not None:
        return Verdict(f"{STOPPED}an image could not be pulled in {waited:.0f} s: {pull}")
    if view.unschedulable is not None:
        why = view.unschedulable
        return Verdict(f"{STOPPED}its pod could not be scheduled in {waited:.0f} s: {why}")
    if view.count == 0:
        return Verdict(f"{STOPPED}no pod was created in {waited:.0f} s{warning()}")
    return Verdict(f"{STOPPED}its pod stayed pending for {waited:.0f} s{warning()}")


def _unschedulable(status: Any) -> str | None:
    if status.phase != "Pending":
        return None
    for condition in status.conditions or []:
        if (
            condition.type == "PodScheduled"
            and condition.status == "False"
            and condition.reason == "Unschedulable"
        ):
            return condition.message or "Unschedulable"
    return None


def _event_time(event: Any) -> float:
    for value in (event.last_timestamp, event.event_time, event.first_timestamp):
        if value is not None:
            return float(value.timestamp())
    return 0.0


def _ending(terminated: Any) -> str:
    if terminated.reason == "OOMKilled":
        return "the policy container was killed for exceeding its memory limit (OOMKilled)"
    return f"the policy container exited with code {terminated.exit_code}"


_EPISODE_LINE = re.compile(r"^manieval: run (\d+) episode \d+:", re.MULTILINE)


def progress_in(logs: Sequence[str], plan: EvaluationPlan) -> dict[str, Any]:
    """A running evaluation's progress from its evaluators' logs so far."""
    done, last = episodes_in(logs)
    progress: dict[str, Any] = {"done": done, "total": plan.episode_count()}
    if last is not None and last < len(plan.runs):
        run = plan.runs[last]
        progress |= {"task": run.env_id, "condition": run.condition.name}
    return progress


def episodes_in(logs: Sequence[str]) -> tuple[int, int | None]:
    """Episodes the evaluator logs report done, and the run index of the last one."""
    done, last = 0, None
    for text in logs:
        for match in _EPISODE_LINE.finditer(text):
            done += 1
            last = int(match.group(1))
    return done, last
