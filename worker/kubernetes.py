"""Evaluations as Kubernetes Jobs: a pure builder for the manifest, a thin client for its life.

`build_job` turns a JobSpec into the Job manifest, a plain dict, without I/O. The evaluator is
the pod's main container; the participant's pinned image runs as a native sidecar (an init
container with `restartPolicy: Always`, Kubernetes >= 1.29), which the kubelet stops once the
evaluator has exited: a policy that never exits cannot hold the pod, and its exit code never
decides the pod's outcome. Both containers run under the "restricted" Pod Security profile,
with no service-account token and no service links. They share one memory-backed emptyDir that
holds the evaluator's Unix socket; the policy mounts it read-only (connecting to a socket needs
no write access to the mount) and gets nothing else: no other volume, no env but
MANIEVAL_ENDPOINT. `KubernetesExecutor` creates, adopts, reads, and deletes those Jobs.
"""

from __future__ import annotations

import random
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Any, Literal, TypeVar

import urllib3
from kubernetes.client import (
    ApiClient,
    ApiException,
    BatchV1Api,
    CoreV1Api,
    V1DeleteOptions,
    V1Job,
    V1Pod,
)

from evaluator.endpoint import SOCKET_NAME
from evaluator.job import (
    ENDPOINT_DIR,
    ENDPOINT_DIR_ENV,
    JOB_SPEC_ENV,
    POLICY_ENV,
    SHARDS_ENV,
    EvaluationJob,
)
from evaluator.plan import EvaluationPlan
from evaluator.suite import Limits
from manieval_sdk.serve import ENDPOINT_ENV

APP_LABEL = "app.kubernetes.io/name"
SUBMISSION_LABEL = "manieval.io/submission"
ATTEMPT_LABEL = "manieval.io/attempt"
ROLE_LABEL = "manieval.io/role"
INDEX_LABEL = "batch.kubernetes.io/job-completion-index"  # set by the Job controller
APP, ROLE = "manieval", "evaluation"
EVALUATOR, POLICY = "evaluator", "policy"
EVALUATOR_UID, POLICY_UID, SHARED_GID = 10001, 10002, 10000
ENDPOINT_MOUNT = str(PurePosixPath(ENDPOINT_DIR).parent)
SOCKET = f"unix://{ENDPOINT_DIR}/{SOCKET_NAME}"
GPU_RESOURCE = "nvidia.com/gpu"
MAX_SHARDS = 64
MAX_PAYLOAD_BYTES = 100_000  # one env string may not exceed 128 KiB (Linux MAX_ARG_STRLEN)
_QUANTITY = re.compile(r"^(\d+(\.\d*)?|\.\d+)([KMGTPE]i|[numkMGTPE]|[eE][+-]?\d+)?$")
_DNS_LABEL = re.compile(r"^[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?$")
_DNS_NAME = re.compile(r"^[a-z0-9]([-a-z0-9.]{0,251}[a-z0-9])?$")
_PINNED = re.compile(r"^[a-z0-9][^\s@]*@sha256:[0-9a-f]{64}$")


@dataclass(frozen=True)
class Resources:
    """One container's cpu, memory and ephemeral storage: requested and limited alike."""

    cpu: str
    memory: str
    ephemeral_storage: str

    def as_dict(self) -> dict[str, str]:
        """As Kubernetes names them."""
        return {"cpu": self.cpu, "memory": self.memory, "ephemeral-storage": self.ephemeral_storage}


@dataclass(frozen=True)
class JobSpec:
    """Everything the Job of one attempt of one submission is built from."""

    submission_id: int
    attempt: int
    namespace: str
    evaluator_image: str
    policy_image: str
    evaluation: EvaluationJob
    evaluator_resources: Resources = Resources(cpu="2", memory="4Gi", ephemeral_storage="2Gi")
    policy_resources: Resources = Resources(cpu="1", memory="2Gi", ephemeral_storage="1Gi")
    gpu: bool = False
    active_deadline_seconds: int = 8400
    ttl_seconds_after_finished: int = 3600
    runtime_class_name: str | None = None
    """Pod-level: with gVisor it sandboxes the evaluator as well as the policy."""
    shards: int = 1
    scratch_size: str = "1Gi"
    evaluator_command: tuple[str, ...] = ("manieval", "evaluate-job")

    def __post_init__(self) -> None:
        problems = list(self._problems())
        if problems:
            raise ValueError("invalid job spec: " + "; ".join(problems))

    def _problems(self) -> Iterable[str]:
        if self.submission_id < 1 or self.attempt < 1:
            yield "submission_id and attempt must be at least 1"
        if not _DNS_LABEL.match(self.namespace):
            yield f"namespace {self.namespace!r} is not a DNS label"
        if not _PINNED.match(self.policy_image):
            yield f"policy image {self.policy_image!r} is not pinned by digest"
        if not self.evaluator_image or any(c.isspace() for c in self.evaluator_image):
            yield "the evaluator image is empty or has blanks"
        for value in (*_values(self.evaluator_resources, self.policy_resources), self.scratch_size):
            number = _QUANTITY.match(value)
            if number is None or not any(c in "123456789" for c in number.group(1)):
                yield f"{value!r} is not a positive quantity"
        if self.active_deadline_seconds < 1 or self.ttl_seconds_after_finished < 0:
            yield "the deadline must be positive and the TTL not negative"
        if self.runtime_class_name is not None and not _DNS_NAME.match(self.runtime_class_name):
            yield f"runtime class {self.runtime_class_name!r} is not a DNS name"
        if not 1 <= self.shards <= MAX_SHARDS:
            yield f"shards must be within 1..{MAX_SHARDS}"
        if not self.evaluator_command:
            yield "the evaluator command is empty"
        if len(self.evaluation.canonical_json().encode()) > MAX_PAYLOAD_BYTES:
            yield f"the evaluation spec exceeds {MAX_PAYLOAD_BYTES} bytes"
        try:
            plan = self.evaluation.plan()
        except ValueError as exc:
            yield f"the evaluation spec is invalid: {exc}"
        else:
            if needs_gpu(plan) and not self.gpu:
                yield "the suite simulates on physx_cuda: gpu must be set"

    @property
    def name(self) -> str:
        """The Job's name, the same for every try of this attempt."""
        return job_name(self.submission_id, self.attempt)


def _values(*resources: Resources) -> list[str]:
    return [value for r in resources for value in r.as_dict().values()]


def job_name(submission_id: int, attempt: int) -> str:
    """`eval-<submission>-<attempt>`."""
    return f"eval-{submission_id}-{attempt}"


def job_labels(submission_id: int, attempt: int) -> dict[str, str]:
    """The labels on the Job and its pods (the NetworkPolicy selects the pods by them)."""
    return {
        APP_LABEL: APP,
        SUBMISSION_LABEL: str(submission_id),
        ATTEMPT_LABEL: str(attempt),
        ROLE_LABEL: ROLE,
    }


def needs_gpu(plan: EvaluationPlan) -> bool:
    """Whether any task of the plan simulates on the GPU."""
    return any(run.sim_backend == "physx_cuda" for run in plan.runs)


def active_deadline_for(limits: Limits, *, startup_s: int = 900) -> int:
    """The Job's deadline: the budget, the connect timeout, and time to schedule and pull."""
    return int(limits.budget_s + limits.connect_timeout_s) + startup_s


def build_job(spec: JobSpec) -> dict[str, Any]:
    """The Job manifest of `spec`: the same spec always gives the same dict."""
    labels = job_labels(spec.submission_id, spec.attempt)
    job_spec: dict[str, Any] = {
        "backoffLimit": 0,
        "activeDeadlineSeconds": spec.active_deadline_seconds,
        "ttlSecondsAfterFinished": spec.ttl_seconds_after_finished,
        "podFailurePolicy": {
            "rules": [
                {
                    "action": "Ignore",  # evicted or preempted: not the policy's fault, rerun
                    "onPodConditions": [{"type": "DisruptionTarget", "status": "True"}],
                },
                {
                    "action": "FailJob",  # the evaluator itself broke: ours, never retried
                    "onExitCodes": {"containerName": EVALUATOR, "operator": "NotIn", "values": [0]},
                },
            ]
        },
        "template": {"metadata": {"labels": dict(labels)}, "spec": _pod_spec(spec)},
    }
    if spec.shards > 1:
        job_spec.update(completionMode="Indexed", completions=spec.shards, parallelism=spec.shards)
    return {
        "apiVersion": "batch/v1",
        "kind": "Job",
        "metadata": {"name": spec.name, "namespace": spec.namespace, "labels": labels},
        "spec": job_spec,
    }


def _pod_spec(spec: JobSpec) -> dict[str, Any]:
    pod: dict[str, Any] = {
        "restartPolicy": "Never",
        "automountServiceAccountToken": False,
        "enableServiceLinks": False,
        "terminationGracePeriodSeconds": 10,
        "securityContext": {
            "runAsNonRoot": True,
            "runAsGroup": SHARED_GID,
            "seccompProfile": {"type": "RuntimeDefault"},
        },
        "initContainers": [_policy_container(spec)],
        "containers": [_evaluator_container(spec)],
        "volumes": [
            {"name": "endpoint", "emptyDir": {"medium": "Memory", "sizeLimit": "1Mi"}},
            {"name": "scratch", "emptyDir": {"sizeLimit": spec.scratch_size}},
        ],
    }
    if spec.runtime_class_name is not None:
        pod["runtimeClassName"] = spec.runtime_class_name
    return pod


def _evaluator_container(spec: JobSpec) -> dict[str, Any]:
    resources = spec.evaluator_resources.as_dict()
    if spec.gpu:
        resources[GPU_RESOURCE] = "1"
    env = {
        JOB_SPEC_ENV: spec.evaluation.canonical_json(),
        POLICY_ENV: spec.policy_image,
        SHARDS_ENV: str(spec.shards),
        ENDPOINT_DIR_ENV: ENDPOINT_DIR,
        "HOME": "/tmp",
        "TMPDIR": "/tmp",
    }
    return {
        "name": EVALUATOR,
        "image": spec.evaluator_image,
        "imagePullPolicy": "IfNotPresent",
        "command": list(spec.evaluator_command),
        "env": [{"name": k, "value": v} for k, v in env.items()],
        "resources": {"requests": resources, "limits": dict(resources)},
        "securityContext": _security(EVALUATOR_UID),
        "terminationMessagePolicy": "FallbackToLogsOnError",
        "volumeMounts": [
            {"name": "endpoint", "mountPath": ENDPOINT_MOUNT},
            {"name": "scratch", "mountPath": "/tmp"},
        ],
    }


def _policy_container(spec: JobSpec) -> dict[str, Any]:
    resources = spec.policy_resources.as_dict()
    return {
        "name": POLICY,
        "image": spec.policy_image,
        "imagePullPolicy": "IfNotPresent",
        "restartPolicy": "Always",  # a sidecar: stopped by the kubelet when the evaluator ends
        "env": [{"name": ENDPOINT_ENV, "value": SOCKET}],
        "resources": {"requests": resources, "limits": dict(resources)},
        "securityContext": _security(POLICY_UID),
        "volumeMounts": [{"name": "endpoint", "mountPath": ENDPOINT_MOUNT, "readOnly": True}],
    }


def _security(uid: int) -> dict[str, Any]:
    return {
        "runAsNonRoot": True,
        "runAsUser": uid,
        "runAsGroup": SHARED_GID,
        "privileged": False,
        "allowPrivilegeEscalation": False,
        "readOnlyRootFilesystem": True,
        "capabilities": {"drop": ["ALL"]},
        "seccompProfile": {"type": "RuntimeDefault"},
    }


def build_network_policy(namespace: str) -> dict[str, Any]:
    """Deny all traffic to and from evaluation pods: the policy shares their network."""
    return {
        "apiVersion": "networking.k8s.io/v1",
        "kind": "NetworkPolicy",
        "metadata": {"name": "manieval-evaluations-isolated", "namespace": namespace},
        "spec": {
            "podSelector": {"matchLabels": {APP_LABEL: APP, ROLE_LABEL: ROLE}},
            "policyTypes": ["Ingress", "Egress"],
        },
    }


Phase = Literal["pending", "running", "succeeded", "failed", "deadline_exceeded", "missing"]


@dataclass(frozen=True)
class JobStatus:
    """Where a Job is, from its conditions; `reason` says why it failed."""

    phase: Phase
    reason: str = ""


@dataclass(frozen=True)
class JobRef:
    """A Job of ours as listed: which attempt it runs and where it is."""

    name: str
    submission_id: int
    attempt: int
    status: JobStatus
    terminating: bool


@dataclass(frozen=True)
class StartedJob:
    name: str
    adopted: bool
    """True when the Job already existed (a retried task): it is not created twice."""


class KubernetesError(Exception):
    """The API server refused or failed a request (after retries, when they apply)."""

    def __init__(self, message: str, *, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class JobConflict(KubernetesError):
    """A Job of that name exists but is not this attempt's, or it is being deleted."""


def job_status(job: V1Job) -> JobStatus:
    """A Job's phase from its conditions (Complete, Failed) and its ready pods."""
    status = job.status
    true = {c.type: c for c in (status.conditions or []) if c.status == "True"} if status else {}
    if "Complete" in true:
        return JobStatus("succeeded")
    failed = true.get("Failed")
    if failed is not None:
        reason = f"{failed.reason or 'Failed'}: {failed.message or ''}".rstrip(": ")
        phase: Phase = "deadline_exceeded" if failed.reason == "DeadlineExceeded" else "failed"
        return JobStatus(phase, reason)
    if status is not None and (status.ready or 0) > 0:
        return JobStatus("running")
    return JobStatus("pending")


@dataclass(frozen=True)
class Backoff:
    """Capped exponential backoff with full jitter, for 429 and 5xx answers only."""

    attempts: int = 6
    base_s: float = 0.5
    cap_s: float = 30.0

    def delay(self, retry: int, jitter: float, retry_after: float | None) -> float:
        """Seconds to wait before retry number `retry` (0-based); `jitter` is in [0, 1)."""
        wait = min(self.cap_s, self.base_s * 2.0**retry) * jitter
        if retry_after is not None:
            wait = max(wait, min(retry_after, self.cap_s))
        return wait


T = TypeVar("T")


@dataclass
class KubernetesExecutor:
    """Runs evaluation Jobs in one namespace through the official client."""

    api: ApiClient
    namespace: str
    backoff: Backoff = Backoff()
    sleep: Callable[[float], None] = time.sleep
    jitter: Callable[[], float] = random.random
    request_timeout: tuple[float, float] = (5.0, 30.0)
    _batch: BatchV1Api = field(init=False)
    _core: CoreV1Api = field(init=False)

    def __post_init__(self) -> None:
        self._batch = BatchV1Api(self.api)
        self._core = CoreV1Api(self.api)

    def start(self, spec: JobSpec) -> StartedJob:
        """Create the attempt's Job; if it exists already (409), adopt it when it is ours."""
        if spec.namespace != self.namespace:
            raise ValueError(
                f"this executor runs Jobs in {self.namespace!r}, not {spec.namespace!r}"
            )
        body = V1Job.from_dict(build_job(spec))
        try:
            self._call(self._batch.create_namespaced_job, self.namespace, body)
            return StartedJob(spec.name, adopted=False)
        except KubernetesError as exc:
            if exc.status != 409:
                raise
        existing = self._call(self._batch.read_namespaced_job, spec.name, self.namespace)
        meta = existing.metadata
        labels = (meta.labels if meta else None) or {}
        expected = job_labels(spec.submission_id, spec.attempt)
        if any(labels.get(k) != v for k, v in expected.items()):
            raise JobConflict(f"Job {spec.name} exists with other labels: {labels}", status=409)
        if meta is not None and meta.deletion_timestamp is not None:
            raise JobConflict(f"Job {spec.name} is being deleted; try again later", status=409)
        return StartedJob(spec.name, adopted=True)

    def status(self, submission_id: int, attempt: int) -> JobStatus:
        """Where the attempt's Job is; `missing` when there is none."""
        name = job_name(submission_id, attempt)
        try:
            job = self._call(self._batch.read_namespaced_job, name, self.namespace)
        except KubernetesError as exc:
            if exc.status == 404:
                return JobStatus("missing", f"no Job {name}")
            raise
        return job_status(job)

    def collect(
        self, submission_id: int, attempt: int, *, container: str = EVALUATOR, tail_lines: int = 0
    ) -> list[str]:
        """One container's log per shard index ("" where no pod is left); the evaluator's by
        default, whose last marked block is the result (see evaluator.job.result_from_logs)."""
        name = job_name(submission_id, attempt)
        job = self._call(self._batch.read_namespaced_job, name, self.namespace)
        spec = job.spec
        indexed = spec is not None and spec.completion_mode == "Indexed"
        shards = (spec.completions or 1) if spec is not None and indexed else 1
        selector = ",".join(f"{k}={v}" for k, v in job_labels(submission_id, attempt).items())
        pods = self._call(self._core.list_namespaced_pod, self.namespace, label_selector=selector)
        chosen: dict[int, V1Pod] = {}
        for pod in pods.items:
            index = _pod_index(pod)
            if index not in chosen or _preference(pod) > _preference(chosen[index]):
                chosen[index] = pod
        return [
            self._log(chosen[i], container, tail_lines) if i in chosen else ""
            for i in range(shards)
        ]

    def cancel(self, submission_id: int, attempt: int) -> bool:
        """Delete the Job, its pods first (foreground); False when it was already gone."""
        name = job_name(submission_id, attempt)
        options = V1DeleteOptions(propagation_policy="Foreground")
        try:
            # Not deserialized: the server answers with the Job itself while its pods go.
            response = self._call(
                self._batch.delete_namespaced_job,
                name,
                self.namespace,
                body=options,
                _preload_content=False,
            )
        except KubernetesError as exc:
            if exc.status == 404:
                return False
            raise
        _release(response)
        return True

    def list_jobs(self) -> list[JobRef]:
        """Every evaluation Job in the namespace (by label), with its attempt and status."""
        selector = f"{APP_LABEL}={APP},{ROLE_LABEL}={ROLE}"
        refs: list[JobRef] = []
        token: str | None = None
        while True:
            page = self._call(
                self._batch.list_namespaced_job,
                self.namespace,
                label_selector=selector,
                limit=200,
                _continue=token,
            )
            refs.extend(ref for job in page.items if (ref := _job_ref(job)) is not None)
            token = page.metadata.var_continue if page.metadata else None
            if not token:
                return refs

    def delete_orphans(self, keep: set[tuple[int, int]]) -> list[str]:
        """Delete Jobs of attempts not in `keep` (submission id, attempt); their names."""
        deleted = []
        for ref in self.list_jobs():
            if (ref.submission_id, ref.attempt) in keep or ref.terminating:
                continue
            if self.cancel(ref.submission_id, ref.attempt):
                deleted.append(ref.name)
        return deleted

    def _log(self, pod: V1Pod, container: str, tail_lines: int) -> str:
        name = pod.metadata.name if pod.metadata and pod.metadata.name else ""
        try:
            return self._call(
                self._core.read_namespaced_pod_log,
                name,
                self.namespace,
                container=container,
                tail_lines=tail_lines or None,
            )
        except KubernetesError as exc:
            if exc.status == 400:  # the container has not started: no log yet
                return ""
            raise

    def _call(self, method: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Call the API; retry 429 and 5xx with backoff, raise KubernetesError otherwise."""
        retry = 0
        while True:
            try:
                return method(*args, _request_timeout=self.request_timeout, **kwargs)
            except ApiException as exc:
                status = exc.status if isinstance(exc.status, int) else None
                if _retryable(status) and retry + 1 < self.backoff.attempts:
                    self.sleep(self.backoff.delay(retry, self.jitter(), _retry_after(exc)))
                    retry += 1
                    continue
                raise KubernetesError(_message(exc), status=status) from None
            except urllib3.exceptions.HTTPError as exc:
                raise KubernetesError(f"the API server cannot be reached: {exc}") from None


def _retryable(status: int | None) -> bool:
    return status is not None and (status == 429 or 500 <= status <= 599)


def _retry_after(exc: ApiException) -> float | None:
    value = (exc.headers or {}).get("Retry-After")
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None


def _message(exc: ApiException) -> str:
    import json

    try:
        detail = json.loads(exc.body or "").get("message")
    except (ValueError, AttributeError):
        detail = None
    return f"{exc.status} {exc.reason}: {detail or exc.body or ''}".rstrip(": ")


def _release(response: Any) -> None:
    release = getattr(response, "release_conn", None)
    if callable(release):
        response.drain_conn()
        release()


def _pod_index(pod: V1Pod) -> int:
    meta = pod.metadata
    value = ((meta.labels or {}).get(INDEX_LABEL) if meta else None) or (
        (meta.annotations or {}).get(INDEX_LABEL) if meta else None
    )
    return int(value) if value is not None and value.isdigit() else 0


def _preference(pod: V1Pod) -> tuple[bool, float]:
    """A succeeded pod's log first, else the newest pod's (a disrupted one was replaced)."""
    phase = pod.status.phase if pod.status else None
    created = pod.metadata.creation_timestamp if pod.metadata else None
    return (phase == "Succeeded", created.timestamp() if created else 0.0)


def _job_ref(job: V1Job) -> JobRef | None:
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
    )
