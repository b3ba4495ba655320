"""The life of evaluation Jobs through the official client: create or adopt, watch, read, delete.

`KubernetesExecutor` speaks to one namespace. Only 429 and 5xx answers are retried (with capped,
jittered backoff): a 409 on create adopts the attempt's own Job, anything else is an error the
caller reports. It reads what the pods say (phase, image pulls, the policy container's last
termination) so the worker can give every run a reason, and never trusts a pod with a credential.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
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

from worker.kubernetes.manifest import (
    APP,
    APP_LABEL,
    ATTEMPT_LABEL,
    EVALUATOR,
    INDEX_LABEL,
    POLICY,
    ROLE,
    ROLE_LABEL,
    SUBMISSION_LABEL,
    JobSpec,
    build_job,
    build_secret,
    job_labels,
    job_name,
)

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
    created: datetime | None = None


@dataclass(frozen=True)
class PodView:
    """What an attempt's pods say beyond the Job's conditions."""

    stuck: str | None = None
    """A container that cannot start (its image cannot be pulled, say), and why."""
    policy_ended: str | None = None
    """How the policy container last ended, when it did not exit cleanly (OOMKilled, a code)."""
    evaluating: bool = False
    """Whether an evaluator container has started in some pod."""
    started: int = 0
    """In how many pods the evaluator container has started (an Indexed Job has one per
    shard: one shard left unscheduled holds the whole result)."""
    disrupted: str | None = None
    """How the cluster evicted, preempted or lost a pod of the Job (a DisruptionTarget
    condition, or a pod failed with a reason of the kubelet's such as Evicted or NodeLost)."""
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
ORPHAN_GRACE_S = 120.0
LIST_RESTARTS = 3
MAX_LOG_BYTES = 16 * 1024 * 1024  # an evaluator's log holds the result document: keep it whole


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

    def close(self) -> None:
        """Release the client's connections."""
        self.api.close()  # type: ignore[no-untyped-call]

    def start(self, spec: JobSpec) -> StartedJob:
        """Create the attempt's Job; if it exists already (409), adopt it when it is ours."""
        if spec.namespace != self.namespace:
            raise ValueError(
                f"this executor runs Jobs in {self.namespace!r}, not {spec.namespace!r}"
            )
        body = V1Job.from_dict(build_job(spec))
        try:
            created = self._call(self._batch.create_namespaced_job, self.namespace, body)
        except KubernetesError as exc:
            if exc.status != 409:
                raise
        else:
            self._give_evaluation(spec, created)
            return StartedJob(spec.name, adopted=False)
        existing = self._call(self._batch.read_namespaced_job, spec.name, self.namespace)
        meta = existing.metadata
        labels = (meta.labels if meta else None) or {}
        expected = job_labels(spec.submission_id, spec.attempt)
        if any(labels.get(k) != v for k, v in expected.items()):
            raise JobConflict(f"Job {spec.name} exists with other labels: {labels}", status=409)
        if meta is not None and meta.deletion_timestamp is not None:
            raise JobConflict(f"Job {spec.name} is being deleted; try again later", status=409)
        self._give_evaluation(spec, existing)  # the one who created it may have died first
        return StartedJob(spec.name, adopted=True)

    def give_evaluation(self, spec: JobSpec) -> None:
        """Make sure the attempt's existing Job has its Secret (a watch resumed after its
        creator died between the two)."""
        job = self._call(self._batch.read_namespaced_job, spec.name, self.namespace)
        self._give_evaluation(spec, job)

    def _give_evaluation(self, spec: JobSpec, job: V1Job) -> None:
        """Create the Job's Secret with the evaluation, owned by the Job (deleted with it); the
        pod waits for it. One that exists already (409) is this attempt's: same name, owner."""
        uid = job.metadata.uid if job.metadata is not None else None
        if not uid:
            raise KubernetesError(f"the API server gave Job {spec.name} no uid")
        secret = build_secret(spec, job_uid=uid)  # a dict is sent as it is
        try:
            self._call(self._core.create_namespaced_secret, self.namespace, secret)
        except KubernetesError as exc:
            if exc.status != 409:
                raise

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

    def pods(self, submission_id: int, attempt: int) -> PodView:
        """Look into the attempt's pods: a container that cannot start, how the policy ended."""
        selector = ",".join(f"{k}={v}" for k, v in job_labels(submission_id, attempt).items())
        pods = self._call(self._core.list_namespaced_pod, self.namespace, label_selector=selector)
        view = PodView(names=frozenset((p.metadata.name or "") for p in pods.items if p.metadata))
        for pod in pods.items:
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
            for container in [
                *(status.init_container_statuses or []),
                *(status.container_statuses or []),
            ]:
                view = _look(view, container)
            started = view.evaluating
            view = replace(view, evaluating=before or started, started=view.started + started)
        return view

    def events(self, submission_id: int, attempt: int) -> list[str]:
        """The cluster's warnings about the attempt's Job (a pod the quota refused, say),
        oldest first, as `Reason: message`."""
        name = job_name(submission_id, attempt)
        selector = f"involvedObject.kind=Job,involvedObject.name={name}"
        listed = self._call(
            self._core.list_namespaced_event, self.namespace, field_selector=selector
        )
        warnings = [e for e in listed.items if e.type == "Warning"]
        warnings.sort(key=_event_time)
        return [f"{e.reason or 'Warning'}: {e.message or ''}".rstrip(": ") for e in warnings]

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
        restarts = 0
        while True:
            try:
                page = self._call(
                    self._batch.list_namespaced_job,
                    self.namespace,
                    label_selector=selector,
                    limit=200,
                    _continue=token,
                )
            except KubernetesError as exc:
                # 410 Gone: the continue token expired (compacted); list again from the start.
                if exc.status != 410 or token is None or restarts >= LIST_RESTARTS:
                    raise
                refs, token, restarts = [], None, restarts + 1
                continue
            refs.extend(ref for job in page.items if (ref := _job_ref(job)) is not None)
            token = page.metadata.var_continue if page.metadata else None
            if not token:
                return refs

    def delete_orphans(
        self, keep: set[tuple[int, int]], *, grace_s: float = ORPHAN_GRACE_S
    ) -> list[str]:
        """Delete Jobs of attempts not in `keep` (submission id, attempt); their names.

        Jobs younger than `grace_s` stay: a worker may have claimed its attempt and created the
        Job after the caller read which attempts are active."""
        deleted = []
        young = datetime.now(UTC) - timedelta(seconds=grace_s)
        for ref in self.list_jobs():
            if (ref.submission_id, ref.attempt) in keep or ref.terminating:
                continue
            if ref.created is None or ref.created > young:
                continue
            if self.cancel(ref.submission_id, ref.attempt):
                deleted.append(ref.name)
        return deleted

    def _log(self, pod: V1Pod, container: str, tail_lines: int) -> str:
        """A container's log as text. Read raw and decoded leniently: a policy may print any
        bytes, and the client's own strict decoding would raise on them."""
        name = pod.metadata.name if pod.metadata and pod.metadata.name else ""
        try:
            response: Any = self._call(  # raw: an urllib3 response, not the annotated str
                self._core.read_namespaced_pod_log,
                name,
                self.namespace,
                container=container,
                tail_lines=tail_lines or None,
                limit_bytes=MAX_LOG_BYTES,
                _preload_content=False,
            )
        except KubernetesError as exc:
            if exc.status == 400:  # the container has not started: no log yet
                return ""
            raise
        try:
            return bytes(response.data).decode("utf-8", errors="replace")
        finally:
            _release(response)

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
                # The client's own retries are off (`no_client_retries`): this backoff is the
                # only one, for an unreachable server as for 429 and 5xx.
                if retry + 1 < self.backoff.attempts:
                    self.sleep(self.backoff.delay(retry, self.jitter(), None))
                    retry += 1
                    continue
                raise KubernetesError(f"the API server cannot be reached: {exc}") from None
            except ValueError as exc:  # an answer the client cannot read (bad JSON, a model)
                raise KubernetesError(f"unreadable answer from the API server: {exc}") from None


def no_client_retries(configuration: Any) -> Any:
    """Turn off urllib3's own retries in a client Configuration (it would retry connection
    errors, and 413/429/503 answers with Retry-After, outside `Backoff`); returns it."""
    configuration.retries = urllib3.util.Retry(
        total=0,
        connect=0,
        read=0,
        redirect=0,
        status=0,
        other=0,
        respect_retry_after_header=False,
        raise_on_status=False,
        raise_on_redirect=False,
    )
    return configuration


def _retryable(status: int | None) -> bool:
    return status is not None and (status == 429 or 500 <= status <= 599)


def _retry_after(exc: ApiException) -> float | None:
    value = (exc.headers or {}).get("Retry-After")
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None


def _message(exc: ApiException) -> str:
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
        created=meta.creation_timestamp,
    )


STUCK_REASONS = frozenset(
    {
        "ImagePullBackOff",
        "InvalidImageName",
        "ErrImageNeverPull",
        "CreateContainerConfigError",
        "CreateContainerError",
    }
)
"""Waiting reasons that do not resolve by waiting (ErrImagePull turns into ImagePullBackOff)."""


def _look(view: PodView, container: Any) -> PodView:
    state, last = container.state, container.last_state
    waiting = state.waiting if state is not None else None
    if view.stuck is None and waiting is not None and waiting.reason in STUCK_REASONS:
        detail = f": {waiting.message}" if waiting.message else ""
        view = replace(view, stuck=f"the {container.name} container: {waiting.reason}{detail}")
    if container.name == EVALUATOR and state is not None and (state.running or state.terminated):
        view = replace(view, evaluating=True)
    if container.name == POLICY and view.policy_ended is None:
        for ended in (
            state.terminated if state is not None else None,
            last.terminated if last is not None else None,
        ):
            if ended is not None and (ended.reason == "OOMKilled" or ended.exit_code):
                view = replace(view, policy_ended=_ending(ended))
                break
    return view


DISRUPTING_REASONS = frozenset(
    {"Evicted", "NodeLost", "Preempting", "Shutdown", "Terminated", "NodeShutdown"}
)
"""Reasons a pod fails for that are the node's or the cluster's doing, never the evaluation's."""


def _disruption(name: str, status: Any) -> str | None:
    for condition in status.conditions or []:
        if condition.type == "DisruptionTarget" and condition.status == "True":
            why = condition.reason or "DisruptionTarget"
            detail = f": {condition.message}" if condition.message else ""
            return f"pod {name} was disrupted by the cluster ({why}{detail})"
    if status.phase == "Failed" and status.reason in DISRUPTING_REASONS:
        detail = f": {status.message}" if status.message else ""
        return f"pod {name} failed on its node ({status.reason}{detail})"
    return None


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
