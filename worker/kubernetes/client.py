"""The life of evaluation Jobs through the official client: create or adopt, watch, read, delete.

`KubernetesExecutor` speaks to one namespace. Only 429 and 5xx answers are retried (with capped,
jittered backoff): a 409 on create adopts the attempt's own Job, anything else is an error the
caller reports (`KubernetesError`). What it reads (Job conditions, pods, events) is interpreted
by `worker.kubernetes.status`; this module holds only the I/O, and never trusts a pod with a
credential.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Any, TypeVar

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
    EVALUATOR,
    ROLE,
    ROLE_LABEL,
    JobSpec,
    build_job,
    build_secret,
    job_labels,
    job_name,
)
from worker.kubernetes.quota import Quota, quota_of
from worker.kubernetes.status import (
    JobRef,
    JobStatus,
    PodView,
    job_ref,
    job_status,
    pod_view,
    pods_by_index,
    warnings,
)
from worker.settings import WorkerSettings


@dataclass(frozen=True)
class StartedJob:
    name: str
    adopted: bool
    """True when the Job already existed (a retried task): it is not created twice."""
    uid: str = field(default="", compare=False)
    """The Job's uid: the cluster's events about it name it (a Job made again has a new one)."""


class KubernetesError(Exception):
    """The API server refused or failed a request (after retries, when they apply)."""

    def __init__(self, message: str, *, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class JobConflict(KubernetesError):
    """A Job of that name exists but is not this attempt's, or it is being deleted."""


class LogLost(KubernetesError):
    """An evaluator's log cannot be read at the end: its pod is gone (garbage-collected with a
    node removed) or its node does not answer the kubelet proxy. The cluster's doing."""


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

    @property
    def batch(self) -> BatchV1Api:
        return self._batch

    @property
    def core(self) -> CoreV1Api:
        return self._core

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
            self._give_evaluation(spec, created, fresh=True)
            return StartedJob(spec.name, adopted=False, uid=_uid(created))
        existing = self._call(self._batch.read_namespaced_job, spec.name, self.namespace)
        meta = existing.metadata
        labels = (meta.labels if meta else None) or {}
        expected = job_labels(spec.submission_id, spec.attempt)
        if any(labels.get(k) != v for k, v in expected.items()):
            raise JobConflict(f"Job {spec.name} exists with other labels: {labels}", status=409)
        if meta is not None and meta.deletion_timestamp is not None:
            raise JobConflict(f"Job {spec.name} is being deleted; try again later", status=409)
        self._give_evaluation(spec, existing)  # the one who created it may have died first
        return StartedJob(spec.name, adopted=True, uid=_uid(existing))

    def quotas(self) -> list[Quota]:
        """The namespace's ResourceQuotas, with their limits and what is used."""
        listed = self._call(self._core.list_namespaced_resource_quota, self.namespace)
        return [quota_of(q) for q in listed.items]

    def give_evaluation(self, spec: JobSpec) -> None:
        """Make sure the attempt's existing Job has its Secret (a watch resumed after its
        creator died between the two)."""
        job = self._call(self._batch.read_namespaced_job, spec.name, self.namespace)
        self._give_evaluation(spec, job)

    def _give_evaluation(self, spec: JobSpec, job: V1Job, *, fresh: bool = False) -> None:
        """Create the Job's Secret with the evaluation, owned by the Job (deleted before it); the
        pod waits for it. For an adopted Job one that exists (409) is its own. For a Job just
        created (`fresh`) it is a deleted predecessor's, left to the garbage collector by a
        deletion that did not wait for it (ours do): waited out, or an error (the attempt runs
        again under other names), never adopted to vanish under the new pod."""
        uid = job.metadata.uid if job.metadata is not None else None
        if not uid:
            raise KubernetesError(f"the API server gave Job {spec.name} no uid")
        secret = build_secret(spec, job_uid=uid)  # a dict is sent as it is
        for retry in range(self.backoff.attempts):
            try:
                self._call(self._core.create_namespaced_secret, self.namespace, secret)
                return
            except KubernetesError as exc:
                if exc.status != 409:
                    raise
                if not fresh:
                    return  # the adopted Job's own, made by whoever created the Job
            if retry + 1 < self.backoff.attempts:
                self.sleep(self.backoff.delay(retry, self.jitter(), None))
        name = secret["metadata"]["name"]
        message = f"Secret {name} of a deleted Job {spec.name} is still there"
        raise KubernetesError(message, status=409)

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

    def logs(
        self, pods: list[V1Pod], shards: int, *, container: str = EVALUATOR, tail_lines: int = 0
    ) -> list[str]:
        """One container's log per shard index of the Job whose `pods` these are (one request
        per shard; "" where no pod is left or its container has not started)."""
        chosen = pods_by_index(pods)
        return [
            self._log(chosen[i], container, tail_lines) if i in chosen else ""
            for i in range(shards)
        ]

    def result_logs(
        self, submission_id: int, attempt: int, shards: int
    ) -> tuple[list[V1Pod], list[str]]:
        """The attempt's pods listed now and each shard's evaluator log, for the result; `LogLost`
        when a shard's pod is gone or its log cannot be read (404, 5xx)."""
        pods = self.job_pods(submission_id, attempt)
        missing = sorted(set(range(shards)) - set(pods_by_index(pods)))
        if missing:
            raise LogLost(f"no pod of shard {missing[0]} is left to read its log from")
        return pods, self.logs(pods, shards)

    def job_pods(self, submission_id: int, attempt: int) -> list[V1Pod]:
        """The attempt's pods, listed now by its labels."""
        selector = ",".join(f"{k}={v}" for k, v in job_labels(submission_id, attempt).items())
        pods = self._call(self._core.list_namespaced_pod, self.namespace, label_selector=selector)
        return list(pods.items)

    def pods(self, submission_id: int, attempt: int) -> PodView:
        """Look into the attempt's pods: a container that cannot start, how the policy ended;
        and into its Job, which records a disruption that failed it after its pods are gone
        (a worker restarted since the eviction sees only the Job)."""
        pods = self.job_pods(submission_id, attempt)
        return pod_view(pods, job=self.status(submission_id, attempt))

    def events(self, submission_id: int, attempt: int, *, uid: str = "") -> list[str]:
        """The cluster's warnings about the attempt's Job (a pod the quota refused, say),
        oldest first, as `Reason: message`; with `uid`, only about that Job, not an earlier
        one of the same name."""
        name = job_name(submission_id, attempt)
        selector = f"involvedObject.kind=Job,involvedObject.name={name}"
        if uid:
            selector += f",involvedObject.uid={uid}"
        listed = self._call(
            self._core.list_namespaced_event, self.namespace, field_selector=selector
        )
        return warnings(listed.items)

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
            refs.extend(ref for job in page.items if (ref := job_ref(job)) is not None)
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
            if exc.status == 404 or (exc.status or 0) >= 500:  # the pod or its node is gone
                raise LogLost(f"the log of pod {name}: {exc}", status=exc.status) from None
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


def _uid(job: V1Job) -> str:
    return (job.metadata.uid if job.metadata is not None else None) or ""


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


def kubernetes_executor(settings: WorkerSettings) -> KubernetesExecutor:
    """An executor for the configured cluster: in-cluster service account, an API URL without
    credentials (`kubectl proxy`, tests), or a kubeconfig."""
    from kubernetes import config
    from kubernetes.client import ApiClient, Configuration

    configuration = Configuration()
    if settings.k8s_api_url:
        configuration.host = settings.k8s_api_url
    elif settings.k8s_in_cluster:
        config.load_incluster_config(client_configuration=configuration)  # type: ignore[no-untyped-call]
    else:
        path = str(settings.k8s_kubeconfig) if settings.k8s_kubeconfig else None
        config.load_kube_config(  # type: ignore[no-untyped-call]
            config_file=path, client_configuration=configuration
        )
    no_client_retries(configuration)
    return KubernetesExecutor(ApiClient(configuration), settings.k8s_namespace)
