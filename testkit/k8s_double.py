"""An HTTP test double of the Kubernetes API server, with just the endpoints the worker uses.

No API server can run on this machine, so the official client talks over HTTP to this one:
batch/v1 Jobs (create, read, list by label with pagination, delete with a propagation policy),
core/v1 pods (list by label, read a container's log), events (list by involved object) and
ResourceQuotas (listed with what they use, as the quota controller reports it).
Created Jobs are checked against the official schema, strictly, as the real server's validation
would refuse them. Tests play the Job controller and the kubelet (`run`, `succeed`, `fail`,
`exceed_deadline`), queue faults for the next matching requests, and inspect every request
received. The cluster keeps its own time (`clock`, `testkit.k8s_clock`): a Job's startTime is
set when it is created, and when a test advances the clock (`advance`) past startTime +
activeDeadlineSeconds, the controller fails the Job with reason DeadlineExceeded, in the order
of its version (`controller`).

Where the real server behaves in a way that surprises clients, the double does the same: a
foreground deletion answers with the Job itself (not a Status), batch/v1 deletes without a
propagation policy orphan the pods, and logs come back as text/plain. And where real clusters
fail in ways the worker must tell apart from the policy's failures, the double fails alike:
evicted pods are deleted, the Job's podFailurePolicy deciding whether the Job fails or a new
pod replaces them (`evict`, `disrupt`, `testkit.k8s_pod_failure_policy`),
pods stay Pending with an Unschedulable condition, a ResourceQuota refuses Jobs (403 on create)
or pods (the Job controller records a FailedCreate warning and makes no pod), and an expired
list continuation answers `410 Gone`. An image pull fails and is retried as the kubelet does
(`cannot_pull`, then `pulled`), a node's kubelet refuses pods at admission (`refuse`), logs go
with their pods (`collect_pods`) or cannot be reached through the kubelet proxy
(`lose_kubelet`), the garbage collector takes a deleted Job's Secret on a later pass unless it
blocks the Job's foreground deletion (`collect_garbage`, `gc_paused`), a proxy can cut
watches (`watch_cut_after`) and a restart ends every open one (`cut_watches`).

Jobs and pods can be watched as on a real server (`?watch=true`): newline-delimited events
(ADDED, MODIFIED, DELETED, BOOKMARK when `allowWatchBookmarks`, once a minute of the cluster's
clock as the watch cache sends them, ERROR), a resourceVersion per object and per list,
`resourceVersion` to resume from, `timeoutSeconds` ending the stream, and
`410 Gone` (an ERROR event holding a Status, as the real server sends it inside the stream) for
a version older than the history kept (`expire_watches`, `history_limit`). Every change to a Job
or pod, through the methods above or by editing `jobs` and `pods` directly, becomes an event:
the double compares the objects with what it last published (`together` publishes a block's
changes as one, `caught_up` says whether a watcher's version has them all). `counts` tells the
requests by kind (`watch pods`, `list jobs`, `get pods/log`, ...).
"""

from __future__ import annotations

import base64
import bisect
import copy
import functools
import json
import re
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from decimal import Decimal
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Concatenate, Literal, ParamSpec, TypeVar
from urllib.parse import parse_qs, urlsplit

import kubernetes_validate
from kubernetes.client import ApiClient, Configuration
from kubernetes.utils import parse_quantity

from testkit.k8s_clock import (
    DEADLINE_EXCEEDED,
    DEADLINE_MESSAGE,
    ClusterClock,
    decided,
    past_active_deadline,
)
from testkit.k8s_pod_failure_policy import POD_FAILURE_POLICY, match_pod_failure_policy
from worker.kubernetes.client import Backoff, KubernetesExecutor, no_client_retries
from worker.kubernetes.manifest import EVALUATOR, INDEX_LABEL, job_name

NAMESPACE = "manieval-eval"
SCHEMA_VERSION = "1.30"
DIGEST = "sha256:" + "ab" * 32
POLICY_IMAGE = f"127.0.0.1:5000/alice/policy@{DIGEST}"
EVALUATOR_IMAGE = f"127.0.0.1:5000/manieval/evaluator@sha256:{'cd' * 32}"

Json = dict[str, Any]
Controller = Literal["1.29", "1.31"]
CONTROLLERS: tuple[Controller, ...] = ("1.29", "1.31")
"""The Job controllers whose ordering the executor's tests run against (`ApiServerDouble`)."""
_JOBS = re.compile(r"^/apis/batch/v1/namespaces/([^/]+)/jobs(?:/([^/]+))?$")
_PODS = re.compile(r"^/api/v1/namespaces/([^/]+)/pods(?:/([^/]+)/log)?$")
_EVENTS = re.compile(r"^/api/v1/namespaces/([^/]+)/events$")
_SECRETS = re.compile(r"^/api/v1/namespaces/([^/]+)/secrets$")
_QUOTAS = re.compile(r"^/api/v1/namespaces/([^/]+)/resourcequotas$")
_TERMINAL = ("Succeeded", "Failed")
_STAMP = "%Y-%m-%dT%H:%M:%SZ"
_KINDS = {"jobs": ("Job", "batch/v1"), "pods": ("Pod", "v1")}
_WATCHING = ("1", "true")
P = ParamSpec("P")
R = TypeVar("R")


def _publishes(
    method: Callable[Concatenate[ApiServerDouble, P], R],
) -> Callable[Concatenate[ApiServerDouble, P], R]:
    """After the method, what it changed is published to the watches."""

    @functools.wraps(method)
    def published(self: ApiServerDouble, *args: P.args, **kwargs: P.kwargs) -> R:
        with self.lock:
            answer = method(self, *args, **kwargs)
            namespace, name = [*args, None, None][:2]
            if isinstance(namespace, str) and isinstance(name, str):
                self._dirty.add((namespace, name))  # the Job `name` and its pods
            else:
                self._scan_all = True
            self._sync()
            return answer

    return published


@dataclass(frozen=True)
class WatchRequest:
    """A watch of `store` ("jobs" or "pods") in `namespace`, to be streamed."""

    store: str
    namespace: str
    query: dict[str, list[str]]
    opened_at: float = 0.0
    """The cluster's clock (`ClusterClock.elapsed_s`) when the request came: its bookmark
    timer starts there."""
    cuts: int = 0
    """`cut_watches` calls before the request came: a later one ends it."""


@dataclass
class Fault:
    method: str
    path_part: str
    status: int
    retry_after: int | None = None
    apply: bool = False
    """Process the request anyway, then answer with the error (a lost response)."""


@dataclass
class Recorded:
    method: str
    path: str
    query: dict[str, list[str]]
    body: Any


@dataclass
class ApiServerDouble:
    """In-memory Jobs, pods and logs behind an HTTP server on 127.0.0.1."""

    jobs: dict[tuple[str, str], Json] = field(default_factory=dict)
    pods: dict[tuple[str, str], Json] = field(default_factory=dict)
    logs: dict[tuple[str, str, str], str] = field(default_factory=dict)
    requests: list[Recorded] = field(default_factory=list)
    deletions: list[tuple[str, str | None]] = field(default_factory=list)
    faults: list[Fault] = field(default_factory=list)
    events: list[Json] = field(default_factory=list)
    secrets: dict[tuple[str, str], Json] = field(default_factory=dict)
    """Created Secrets; the garbage collector deletes those a deleted Job owned."""
    hold_deletions: bool = False
    """Foreground deletions leave the Job terminating until `finish_deletions`."""
    gc_paused: bool = False
    """The garbage collector is behind: it makes no pass of its own (tests make them with
    `collect_garbage`) and foreground deletions wait for it."""
    gc_every: float = 0.05
    """Seconds between the garbage collector's passes (`collect_garbage`)."""
    watch_cut_after: float | None = None
    """A proxy in front of the server cuts every watch after this many seconds (0: at once,
    once it has sent what it had ready), whatever its `timeoutSeconds`."""
    job_quota: int | None = None
    """A ResourceQuota's `count/jobs.batch`: creating a Job beyond it answers 403."""
    pod_quota: int | None = None
    """A ResourceQuota's `pods`: the controller's pod creations beyond it are refused."""
    compute_quota: dict[str, str] = field(default_factory=dict)
    """A ResourceQuota's compute resources (`requests.cpu`, `limits.memory`, `cpu`, ...):
    the controller's pod creations beyond it are refused. A pod counts its containers' requests
    or limits and its RuntimeClass's overhead (`_pod_usage`)."""
    runtime_classes: dict[str, dict[str, str]] = field(default_factory=dict)
    """RuntimeClasses by name, each with its `overhead.podFixed` (cpu, memory)."""
    quotas_readable: bool = True
    """False: listing ResourceQuotas is forbidden (403), as with a Role that does not grant it."""
    on_create: Callable[[str, str], object] | None = None
    """Plays the Job controller the moment a Job is created (namespace, name)."""
    expire_continue: bool = False
    """Continue tokens have expired: a list with one answers 410 Gone."""
    controller: Controller = "1.31"
    """How the Job controller ends a Job. "1.31" (and later; `delayTerminalCondition()` in
    pkg/controller/job/job_controller.go, on by default from 1.31): it first writes
    FailureTarget or SuccessCriteriaMet, ends the Job's running pods (deleted through a
    terminating phase: a deletionTimestamp while the job-tracking finalizer holds them), and
    adds Failed or Complete only once none is left terminating (`settle`). "1.29": the
    terminal condition at once (after a FailureTarget only when the podFailurePolicy failed
    the Job), and running pods are deleted at once."""
    bookmark_every: float = 60.0
    """Seconds of the cluster's clock between BOOKMARK events on a watch that allows them. The
    watch cache sends them "roughly every minute" (`bookmarkFrequency` in
    staging/src/k8s.io/apiserver/pkg/storage/cacher/cacher.go; each watcher's
    `nextBookmarkTime` in cache_watcher.go), so a quiet watch goes a minute without a word.
    They come as the clock passes them (`advance`, and the second each change takes), never
    on the wall clock. (The real cache also sends one just before the watch's deadline, which
    the double keeps on the wall clock; it sends none there.)"""
    scan_every: float = 0.1
    """Seconds between looks for changes made by editing `jobs` or `pods` directly."""
    history_limit: int = 100_000
    """Events kept for watches to resume from; older versions answer 410 Gone."""
    clock: ClusterClock = field(default_factory=ClusterClock)
    """The cluster's time (`testkit.k8s_clock`): timestamps, Jobs' startTime and deadlines.
    Tests move it with `advance`, never by waiting."""
    lock: threading.RLock = field(default_factory=threading.RLock)
    _version: int = 1  # the cluster's history began before the test: never "0" (any)
    _compacted: int = 0
    _expiries: int = 0
    _cuts: int = 0
    """How many times every open watch was cut (`cut_watches`)."""
    _history: list[tuple[str, Json]] = field(default_factory=list)
    _history_versions: list[int] = field(default_factory=list)
    _published: dict[tuple[str, str, str], Json] = field(default_factory=dict)
    _last_scan: float = 0.0
    _closed: bool = False
    _unreachable: set[tuple[str, str]] = field(default_factory=set)
    """Pods (namespace, name) whose node the API server cannot reach through the kubelet."""
    _held: int = 0
    _dirty: set[tuple[str, str]] = field(default_factory=set)
    """Jobs (namespace, name) whose Job or pods a method changed: published at the next sync."""
    _scan_all: bool = False

    def __post_init__(self) -> None:
        self._changes = threading.Condition(self.lock)
        double = self

        class Handler(_Handler):
            server_double = double

        self._server = _Server(("127.0.0.1", 0), Handler)
        self._server.daemon_threads = True
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
        )
        self._collector = threading.Thread(target=self._collect_forever, daemon=True)

    @property
    def host(self) -> str:
        return f"http://127.0.0.1:{self._server.server_address[1]}"

    def __enter__(self) -> ApiServerDouble:
        self._thread.start()
        self._collector.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        with self._changes:
            self._closed = True
            self._changes.notify_all()
        self._server.shutdown()
        self._server.server_close()

    # What tests arrange.

    def fail_next(
        self,
        method: str,
        path_part: str,
        *statuses: int,
        retry_after: int | None = None,
        apply: bool = False,
    ) -> None:
        """Answer the next requests matching `method` and `path_part` with these statuses."""
        with self.lock:
            self.faults += [Fault(method, path_part, s, retry_after, apply) for s in statuses]

    def clear_faults(self) -> None:
        """Answer every request normally again (the faults not yet used are dropped)."""
        with self.lock:
            self.faults.clear()

    @_publishes
    def put_job(self, manifest: Json) -> Json:
        """Store a Job as if someone had created it earlier."""
        with self.lock:
            return self._create_job(manifest["metadata"]["namespace"], copy.deepcopy(manifest))

    @_publishes
    def run(self, namespace: str, name: str, *, ready: bool = True) -> list[str]:
        """The controller creates the pods; with `ready`, the kubelet has started them. Pods
        the ResourceQuota refuses are not made: a FailedCreate warning on the Job says why."""
        with self.lock:
            job = self.jobs[(namespace, name)]
            pods = []
            for index in _indexes(job):
                refusal = self._quota_refusal(namespace, job["spec"]["template"]["spec"])
                if refusal is not None:
                    self._quota_refused_pod(job, refusal)
                    continue
                pods.append(self._add_pod(job, index, ready=ready))
            count = len(pods)
            job["status"].update(active=count, ready=count if ready else 0)
            job["status"].setdefault("startTime", self._now())  # a Job a test stored as it is
            return pods

    @_publishes
    def succeed(
        self,
        namespace: str,
        name: str,
        logs: Sequence[str],
        *,
        policy_logs: Sequence[str] = (),
    ) -> None:
        """Every pod's evaluator exits 0 having printed `logs[index]`; the Job completes."""
        with self.lock:
            pods = self._pods_of(namespace, name) or [
                self.pods[(namespace, p)] for p in self.run(namespace, name)
            ]
            pods = [p for p in pods if p["status"]["phase"] != "Failed"]  # disrupted: replaced
            for pod in pods:
                index = int(pod["metadata"]["labels"].get(INDEX_LABEL, "0"))
                self._evaluator_exits(pod, 0)
                pod["status"]["phase"] = "Succeeded"
                pod_name = pod["metadata"]["name"]
                self.logs[(namespace, pod_name, "evaluator")] = logs[index]
                if index < len(policy_logs):
                    self.logs[(namespace, pod_name, "policy")] = policy_logs[index]
            job = self.jobs[(namespace, name)]
            job["status"].update(active=0, ready=0, succeeded=len(pods), completionTime=self._now())
            if job["spec"].get("completionMode") == "Indexed":
                job["status"]["completedIndexes"] = f"0-{len(pods) - 1}"
            self._conclude(job, "SuccessCriteriaMet", "Complete", "CompletionsReached", "")

    @_publishes
    def fail(
        self,
        namespace: str,
        name: str,
        *,
        reason: str = "PodFailurePolicy",
        message: str = "Container evaluator for pod x failed with exit code 1",
        logs: Sequence[str] = (),
        evaluator_oom: bool = False,
    ) -> None:
        """The pods failed (with `evaluator_oom`, the kubelet killed the evaluator at its memory
        limit: exit code 137, reason OOMKilled); the Job fails with `reason`."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                self._evaluator_exits(pod, 137 if evaluator_oom else 1, oom=evaluator_oom)
                pod["status"]["phase"] = "Failed"
                index = int(pod["metadata"]["labels"].get(INDEX_LABEL, "0"))
                if index < len(logs):
                    self.logs[(namespace, pod["metadata"]["name"], "evaluator")] = logs[index]
            job = self.jobs[(namespace, name)]
            job["status"].update(active=0, ready=0, failed=1)
            self._conclude(job, "FailureTarget", "Failed", reason, message)

    @_publishes
    def advance(self, seconds: float) -> None:
        """Let `seconds` pass on the cluster's clock. The Job controller syncs a Job again when
        its deadline is due (`jm.queue.AddAfter(key, syncDuration)` in `syncJob`,
        pkg/controller/job/job_controller.go): every Job past its deadline fails now."""
        with self.lock:
            self.clock.advance(seconds)
            for job in list(self.jobs.values()):
                if past_active_deadline(job, self.clock.now()):
                    self._deadline_exceeded(job)
            self._changes.notify_all()  # the watches' bookmarks that fell due

    @_publishes
    def exceed_deadline(self, namespace: str, name: str) -> None:
        """The clock reaches the Job's deadline (startTime + activeDeadlineSeconds, `advance`)
        and the controller fails it; a Job without a deadline is failed so all the same."""
        with self.lock:
            job = self.jobs[(namespace, name)]
            if decided(job):  # failed or completed before: its deadline no longer counts
                return
            deadline = job["spec"].get("activeDeadlineSeconds")
            started = (job.get("status") or {}).get("startTime")
            if deadline is not None and started is not None:
                due = datetime.strptime(started, _STAMP).replace(tzinfo=UTC)
                waited = (due - self.clock.now()).total_seconds() + deadline
                self.clock.advance(max(0.0, waited))
            self._deadline_exceeded(job)

    def _deadline_exceeded(self, job: Json) -> None:
        """`syncJob` past `pastActiveDeadline`: a failure condition with reason
        DeadlineExceeded (`newFailureCondition`: FailureTarget first when
        `delayTerminalCondition()`, from 1.31; Failed at once before), and the running pods
        deleted (`deleteActivePods`: terminating under their finalizer until `settle` from
        1.31); pods that failed before stay."""
        meta = job["metadata"]
        for pod in self._pods_of(meta["namespace"], meta["name"]):
            if pod["status"]["phase"] != "Failed":
                self._end_pod(pod)
        job["status"].update(active=0, ready=0, failed=1)
        self._conclude(job, "FailureTarget", "Failed", DEADLINE_EXCEEDED, DEADLINE_MESSAGE)

    @_publishes
    def evict(
        self, namespace: str, name: str, *, reason: str = "EvictionByEvictionAPI"
    ) -> str | None:
        """Evict the Job's pods as a real cluster does: the Eviction API (a node drain goes
        through it) or the scheduler's preemption (`reason="PreemptionByScheduler"`) marks each
        DisruptionTarget, its kubelet ends it (Failed), and it is deleted once the controller
        has counted it (its job-tracking finalizer removed): a worker that was not watching
        (restarted) finds only the Job. The Job's podFailurePolicy decides what follows
        (`_disrupted`): FailJob fails the Job; Ignore makes a replacement, Pending until
        scheduled (its name)."""
        with self.lock:
            return self._disrupted(namespace, name, reason, delete=True)

    @_publishes
    def lose_node(self, namespace: str, name: str) -> None:
        """The pods' node stopped answering: the taint manager marks its pods DisruptionTarget
        (before deleting them) and they are reported with reason NodeLost."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                pod["status"]["conditions"] = [
                    {
                        "type": "DisruptionTarget",
                        "status": "True",
                        "reason": "DeletionByTaintManager",
                        "message": "Taint manager: deleting due to NoExecute taint",
                    }
                ]
                pod["status"]["reason"] = "NodeLost"

    @_publishes
    def unschedulable(
        self,
        namespace: str,
        name: str,
        *,
        message: str = "0/3 nodes are available: 3 Insufficient nvidia.com/gpu.",
    ) -> list[str]:
        """The controller created the pods but the scheduler places none: they stay Pending
        with PodScheduled=False, reason Unschedulable."""
        with self.lock:
            names = self.run(namespace, name, ready=False)
            for pod_name in names:
                self.pods[(namespace, pod_name)]["status"]["conditions"] = [
                    {
                        "type": "PodScheduled",
                        "status": "False",
                        "reason": "Unschedulable",
                        "message": message,
                        "lastProbeTime": None,
                        "lastTransitionTime": self._now(),
                    }
                ]
            return names

    @_publishes
    def disrupt(
        self, namespace: str, name: str, *, reason: str = "EvictionByEvictionAPI"
    ) -> str | None:
        """As `evict`, the failed pods still listed (not yet deleted); under an Ignore rule the
        replacement has started (its name)."""
        with self.lock:
            return self._disrupted(namespace, name, reason, delete=False)

    def _disrupted(self, namespace: str, name: str, reason: str, *, delete: bool) -> str | None:
        """The Job's running pods disrupted with `reason` (a DisruptionTarget condition set
        before the pod is deleted: `addConditionAndDeletePod` in pkg/registry/core/pod/storage/
        eviction.go, PreemptionByScheduler in pkg/scheduler/framework/preemption), then failed; the
        controller matches the first against the Job's podFailurePolicy
        (`testkit.k8s_pod_failure_policy`, as `trackJobStatusAndRemoveFinalizers` does).
        FailJob: the Job fails with reason PodFailurePolicy and the rule's message, its other
        pods ended, in the order of `controller`; no replacement. Ignore: a new pod (its
        name). Count: the backoffLimit of 0 fails the Job (BackoffLimitExceeded)."""
        job = self.jobs[(namespace, name)]
        pods = [p for p in self._pods_of(namespace, name) if p["status"]["phase"] not in _TERMINAL]
        matched = None
        for pod in pods:
            pod["status"]["phase"] = "Failed"
            pod["status"].setdefault("conditions", []).append(
                {
                    "type": "DisruptionTarget",
                    "status": "True",
                    "reason": reason,
                    "message": f"{reason}: the cluster ended the pod",
                    "lastTransitionTime": self._now(),
                }
            )
            matched = matched or match_pod_failure_policy(job, pod)
            if delete:
                del self.pods[(namespace, pod["metadata"]["name"])]
        if matched is None:
            return None
        if matched.action == "Ignore":
            return self._add_pod(job, 0, ready=not delete)
        for pod in self._pods_of(namespace, name):
            if pod["status"]["phase"] not in _TERMINAL:
                self._end_pod(pod)  # another shard's: `deleteActivePods` once the Job fails
        job["status"].update(active=0, ready=0, failed=len(pods))
        if matched.action == "FailJob":
            self._conclude(job, "FailureTarget", "Failed", POD_FAILURE_POLICY, matched.message)
        else:
            limit = "Job has reached the specified backoff limit"
            self._conclude(job, "FailureTarget", "Failed", "BackoffLimitExceeded", limit)
        return None

    def write_log(self, namespace: str, name: str, container: str, text: str) -> None:
        """What a container of the Job's (first) pod has printed so far."""
        with self.lock:
            pod = self._pods_of(namespace, name)[0]
            self.logs[(namespace, pod["metadata"]["name"], container)] = text

    @_publishes
    def cannot_pull(
        self, namespace: str, name: str, container: str, *, reason: str = "ImagePullBackOff"
    ) -> None:
        """The kubelet's pull of `container`'s image failed; the pod stays Pending, the
        container waiting. `EnsureImageExists` (pkg/kubelet/images/image_manager.go) says
        ErrImagePull after a failed try, then ImagePullBackOff while its back-off runs (10 s
        doubling to 300 s: `imageBackOff` in pkg/kubelet/kubelet.go) before the next try:
        tests step through the tries (`reason`), and `pulled` is the try that succeeds."""
        messages = {
            "ErrImagePull": 'failed to pull and unpack image "{image}": failed to resolve '
            'reference "{image}": unexpected status from HEAD request: 503 Service Unavailable',
            "ImagePullBackOff": 'Back-off pulling image "{image}"',
        }
        with self.lock:
            for pod in self._pods_of(namespace, name):
                spec, status = pod["spec"], pod["status"]
                sidecar = any(c["name"] == container for c in spec.get("initContainers", []))
                kind = "initContainerStatuses" if sidecar else "containerStatuses"
                image = next(
                    c["image"]
                    for c in spec["containers"] + spec.get("initContainers", [])
                    if c["name"] == container
                )
                message = messages.get(reason, "{image}").format(image=image)
                statuses = [s for s in status.get(kind, []) if s["name"] != container]
                status[kind] = [
                    *statuses,
                    {
                        "name": container,
                        "image": image,
                        "imageID": "",
                        "ready": False,
                        "restartCount": 0,
                        "state": {"waiting": {"reason": reason, "message": message}},
                    },
                ]

    @_publishes
    def pulled(self, namespace: str, name: str) -> None:
        """The kubelet's next try pulls the images: the Job's pods start (policy, evaluator)."""
        with self.lock:
            pods = self._pods_of(namespace, name)
            for pod in pods:
                self._start_containers(pod)
            self.jobs[(namespace, name)]["status"].update(active=len(pods), ready=len(pods))

    @_publishes
    def refuse(
        self,
        namespace: str,
        name: str,
        *,
        reason: str = "OutOfcpu",
        message: str = "Node didn't have enough resource: cpu, requested: 4000, used: 6000, "
        "capacity: 8000",
        job_fails: bool = True,
    ) -> None:
        """The kubelet of the pods' node refuses them at admission (`Admit` in
        pkg/kubelet/lifecycle/predicate.go: `OutOf<resource>` when its own count of the room
        differs from the scheduler's, UnexpectedAdmissionError when a device plugin's
        allocation fails): they fail at once, never having run, with no DisruptionTarget. No
        podFailurePolicy rule matches a pod without an exit code, so with `job_fails` the
        controller fails the Job on its backoffLimit of 0 (BackoffLimitExceeded)."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                pod["status"] = {"phase": "Failed", "reason": reason, "message": message}
            job = self.jobs[(namespace, name)]
            job["status"].update(active=0, ready=0, failed=1)
            if job_fails:
                limit = "Job has reached the specified backoff limit"
                self._conclude(job, "FailureTarget", "Failed", "BackoffLimitExceeded", limit)

    @_publishes
    def lose_kubelet(self, namespace: str, name: str) -> None:
        """The node of the Job's pods stops answering the API server: the pods stay listed as
        they were, but their logs, read through the kubelet proxy, answer 500 (the API
        server's error dialing the kubelet: `LogLocation` in pkg/registry/core/pod/strategy.go
        and the proxy in staging/src/k8s.io/apiserver/pkg/registry/generic/rest/streamer.go)."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                self._unreachable.add((namespace, pod["metadata"]["name"]))

    @_publishes
    def collect_pods(self, namespace: str, name: str) -> None:
        """The PodGC controller deletes the Job's pods, their node removed after a scale-down
        (`gcOrphaned` in pkg/controller/podgc/gc_controller.go): their logs are gone (404)."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                del self.pods[(namespace, pod["metadata"]["name"])]

    @_publishes
    def policy_killed(self, namespace: str, name: str, *, reason: str = "OOMKilled") -> None:
        """The policy sidecar was killed (and restarted): its last state says how."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                for status in pod["status"].get("initContainerStatuses", []):
                    if status["name"] == "policy":
                        status["restartCount"] += 1
                        status["lastState"] = {
                            "terminated": {"exitCode": 137, "reason": reason, "finishedAt": None}
                        }

    @_publishes
    def settle(self, namespace: str, name: str, *, terminal: bool = True) -> None:
        """Under the 1.31 controller: the kubelet ends the Job's terminating pods, their
        finalizers go, and the controller adds the terminal condition (Failed or Complete)
        after the FailureTarget or SuccessCriteriaMet it wrote first. With `terminal` False,
        only the pods go: the moment a watcher sees them deleted and the Job not yet Failed."""
        with self.lock:
            for pod in self._pods_of(namespace, name):
                if pod["metadata"].get("deletionTimestamp"):
                    del self.pods[(namespace, pod["metadata"]["name"])]
            job = self.jobs.get((namespace, name))
            if job is None or not terminal:
                return  # deleted meanwhile, or the controller has not looked yet
            conditions = job["status"].get("conditions") or []
            final = {"FailureTarget": "Failed", "SuccessCriteriaMet": "Complete"}
            if conditions and conditions[-1]["type"] in final:
                now = self._now()
                last = conditions[-1]
                conditions.append(
                    last
                    | {"type": final[last["type"]], "lastProbeTime": now, "lastTransitionTime": now}
                )

    @_publishes
    def finish_deletions(self) -> None:
        """The garbage collector finishes every pending foreground deletion."""
        with self.lock:
            for key, job in list(self.jobs.items()):
                if job["metadata"].get("deletionTimestamp"):
                    self._finish_foreground(*key)

    def collect_garbage(self) -> None:
        """One pass of the garbage collector (pkg/controller/garbagecollector/
        garbagecollector.go), made every `gc_every` seconds unless `gc_paused`: a Secret whose
        owning Job was gone before the pass is deleted (`attemptToDeleteItem`: its owners are
        absent), and foreground deletions end (not those `hold_deletions` holds). A dependent
        thus lags its owner by a pass, unless its ownerReference has `blockOwnerDeletion`:
        a foreground deletion deletes those before the owner (`processDeletingDependentsItem`)."""
        with self.lock:
            owners = {job["metadata"]["uid"] for job in self.jobs.values()}
            for key, secret in list(self.secrets.items()):
                refs = secret["metadata"].get("ownerReferences") or []
                if refs and not any(ref["uid"] in owners for ref in refs):
                    del self.secrets[key]
            for key, job in list(self.jobs.items()):
                finalizers = job["metadata"].get("finalizers") or []
                if "foregroundDeletion" in finalizers and not self.hold_deletions:
                    self._finish_foreground(*key)
                    self._dirty.add(key)
            self._sync()

    def pods_of(self, namespace: str, name: str) -> list[Json]:
        with self.lock:
            return copy.deepcopy(self._pods_of(namespace, name))

    def created_bodies(self) -> list[Any]:
        """The bodies of every Job creation request (Secrets are in `secrets`)."""
        return [r.body for r in self.requests if r.method == "POST" and r.path.endswith("/jobs")]

    @contextmanager
    def together(self) -> Iterator[None]:
        """What the block changes reaches the watches at once, at its end (as when a watcher
        was slow to look between two changes)."""
        with self.lock:
            self._held += 1
            try:
                yield
            finally:
                self._held -= 1
                self._sync(everything=True)

    def caught_up(self, version: str | None, store: str) -> bool:
        """Whether a watcher of `store` ("jobs" or "pods") at `version` has seen every change
        to it so far. (Its version passes the other store's changes only with a bookmark, a
        minute apart.)"""
        with self.lock:
            self._sync(everything=True)
            if version is None or int(version) < self._compacted:
                return False
            start = bisect.bisect_right(self._history_versions, int(version))
            return all(changed != store for changed, _ in self._history[start:])

    def expire_watches(self) -> None:
        """The history is compacted: open watches end with an ERROR event (410 Gone), and
        resuming from any version seen so far answers 410 too; a fresh list works."""
        with self._changes:
            self._sync(everything=True)
            self._version += 1
            self._compacted = self._version
            self._history.clear()
            self._history_versions.clear()
            self._expiries += 1
            self._changes.notify_all()

    def cut_watches(self) -> None:
        """Every open watch ends at once, with no event (the API server restarts, or a proxy
        drops its connections); resuming from the versions seen still works."""
        with self._changes:
            self._cuts += 1
            self._changes.notify_all()

    def counts(self, since: int = 0) -> Counter[str]:
        """Requests from number `since` on, by verb and resource (`watch pods`, `get jobs`,
        `list events`, `get pods/log`, `create secrets`, ...)."""
        with self.lock:
            recorded = list(self.requests[since:])
        return Counter(_kind_of(r) for r in recorded)

    # The API.

    def handle(self, method: str, url: str, body: Any) -> tuple[tuple[int, Any], int | None]:
        """Answer one request: ((status, payload), Retry-After seconds or None)."""
        parts = urlsplit(url)
        query = parse_qs(parts.query)
        with self.lock:
            self.requests.append(Recorded(method, parts.path, query, copy.deepcopy(body)))
            fault = self._take_fault(method, parts.path)
            if fault is not None and not fault.apply:
                return _error(fault.status), fault.retry_after
            watching = query.get("watch", [""])[0] in _WATCHING
            if (
                method == "GET"
                and watching
                and (match := _JOBS.match(parts.path) or _PODS.match(parts.path))
            ):
                store = "jobs" if "/jobs" in parts.path else "pods"
                watch = WatchRequest(store, match.group(1), query, self.clock.elapsed_s, self._cuts)
                return (200, watch), None
            if method == "GET":
                self._sync()  # a list's resourceVersion covers everything changed before it
            status, payload = self._route(method, parts.path, query, body)
            if method != "GET" and (match := _JOBS.match(parts.path)):
                namespace, name = match.groups()
                name = name or ((body or {}).get("metadata") or {}).get("name", "")
                self._dirty.add((namespace, name))
                self._sync()
            if fault is not None:
                return _error(fault.status), fault.retry_after
            return (status, payload), None

    def stream(self, watch: WatchRequest, send: Callable[[Json], None]) -> None:
        """Serve one watch: `send` each event until `timeoutSeconds`, a 410, or shutdown."""
        query = watch.query
        selector = query.get("labelSelector", [""])[0]
        since = query.get("resourceVersion", [""])[0]
        bookmarks = query.get("allowWatchBookmarks", [""])[0] in _WATCHING
        lasts = float(query.get("timeoutSeconds", ["1800"])[0])
        if self.watch_cut_after is not None:
            lasts = min(lasts, self.watch_cut_after)
        deadline = time.monotonic() + lasts
        kind, api_version = _KINDS[watch.store]

        def ours(event: Json) -> bool:
            meta = event["object"]["metadata"]
            return meta.get("namespace") == watch.namespace and _selects(
                selector, meta.get("labels") or {}
            )

        with self._changes:
            self._sync()
            generation, last = self._expiries, self._version
            pending: list[Json] = []
            if since in ("", "0"):  # no version: the current objects first, as ADDED
                store = self.jobs if watch.store == "jobs" else self.pods
                added = [{"type": "ADDED", "object": copy.deepcopy(o)} for o in store.values()]
                pending = [e for e in added if ours(e)]
            elif int(since) < self._compacted:
                pending, last = [_gone(since)], -1
            else:
                pending, last = self._events_after(watch.store, int(since), generation, ours)
        cuts = watch.cuts
        next_bookmark = watch.opened_at + self.bookmark_every  # on the cluster's clock
        while True:
            for event in pending:
                send(event)
            if last < 0:
                return  # after a 410 the server ends the watch
            now = time.monotonic()
            if now >= deadline or self._closed or self._cuts != cuts:
                return
            if bookmarks and self.clock.elapsed_s >= next_bookmark:
                meta = {"resourceVersion": str(last)}
                send(
                    {
                        "type": "BOOKMARK",
                        "object": {"kind": kind, "apiVersion": api_version, "metadata": meta},
                    }
                )
                next_bookmark = self.clock.elapsed_s + self.bookmark_every
            with self._changes:
                pending, last = self._events_after(watch.store, last, generation, ours)
                if not pending and last >= 0 and self._cuts == cuts:
                    wait = min(self.scan_every, deadline - now)
                    self._changes.wait(max(0.001, wait))

    def _events_after(
        self, store: str, last: int, generation: int, ours: Callable[[Json], bool]
    ) -> tuple[list[Json], int]:
        """The events of `store` after version `last` (with the version now), or a 410."""
        if time.monotonic() - self._last_scan >= self.scan_every:
            self._sync(everything=True)
        if self._expiries != generation or last < self._compacted:
            return [_gone(str(last))], -1
        start = bisect.bisect_right(self._history_versions, last)
        events = [e for s, e in self._history[start:] if s == store and ours(e)]
        return events, self._version

    def _sync(self, *, everything: bool = False) -> None:
        """Publish what changed since the last time, as events: the Jobs (and their pods) the
        methods and requests marked, or with `everything` (and every `scan_every` seconds)
        every object, for what tests edit directly."""
        if self._held:
            return
        keys: set[tuple[str, str, str]] = set()
        if everything or self._scan_all:
            self._last_scan = time.monotonic()
            keys = {("jobs", *k) for k in self.jobs} | {("pods", *k) for k in self.pods}
            keys |= set(self._published)
        for namespace, job in self._dirty:
            keys.add(("jobs", namespace, job))
            keys |= {("pods", *k) for k, pod in list(self.pods.items()) if _job_of(pod) == job}
            keys |= {
                k for k, obj in self._published.items() if k[0] == "pods" and _job_of(obj) == job
            }
        self._dirty.clear()
        self._scan_all = False
        changed = [self._publish(*key) for key in sorted(keys)]
        if any(changed):
            self._changes.notify_all()

    def _publish(self, store: str, namespace: str, name: str) -> bool:
        """Record an event if the object differs from what was last published."""
        obj = (self.jobs if store == "jobs" else self.pods).get((namespace, name))
        old = self._published.get((store, namespace, name))
        if obj is None:
            if old is None:
                return False
            last = copy.deepcopy(self._published.pop((store, namespace, name)))
            self._version += 1
            last["metadata"]["resourceVersion"] = str(self._version)
            self._record(store, "DELETED", last)
            return True
        if old is not None and old == obj:
            return False
        self._version += 1
        obj.setdefault("metadata", {})["resourceVersion"] = str(self._version)
        snapshot = copy.deepcopy(obj)
        self._published[(store, namespace, name)] = snapshot
        self._record(store, "ADDED" if old is None else "MODIFIED", snapshot)
        return True

    def _record(self, store: str, kind: str, obj: Json) -> None:
        self._history.append((store, {"type": kind, "object": obj}))
        self._history_versions.append(self._version)
        if len(self._history) > self.history_limit:
            cut = len(self._history) // 2
            self._compacted = self._history_versions[cut - 1]
            del self._history[:cut], self._history_versions[:cut]

    def _route(
        self, method: str, path: str, query: dict[str, list[str]], body: Any
    ) -> tuple[int, Any]:
        if match := _JOBS.match(path):
            namespace, name = match.groups()
            if name is None and method == "POST":
                return self._post_job(namespace, body)
            if name is None and method == "GET" and self.expire_continue and "continue" in query:
                self.expire_continue = False  # a fresh list gets fresh tokens
                message = "The provided continue parameter is too old to display a consistent list"
                return _status(410, "Expired", message)
            if name is None and method == "GET":
                return 200, self._list("JobList", "batch/v1", self._in(self.jobs, namespace), query)
            if name is not None and method == "GET":
                job = self.jobs.get((namespace, name))
                return (
                    (200, job)
                    if job
                    else _status(404, "NotFound", f'jobs.batch "{name}" not found')
                )
            if name is not None and method == "DELETE":
                return self._delete_job(namespace, name, query, body)
        if (match := _QUOTAS.match(path)) and method == "GET" and not self.quotas_readable:
            return _status(403, "Forbidden", "resourcequotas is forbidden: cannot list")
        if (match := _QUOTAS.match(path)) and method == "GET":
            items = self._quotas(match.group(1))
            return 200, {
                "kind": "ResourceQuotaList",
                "apiVersion": "v1",
                "metadata": {},
                "items": items,
            }
        if (match := _SECRETS.match(path)) and method == "POST":
            return self._post_secret(match.group(1), body)
        if (match := _EVENTS.match(path)) and method == "GET":
            (namespace,) = match.groups()
            events = [e for e in self.events if e["metadata"]["namespace"] == namespace]
            selector = query.get("fieldSelector", [""])[0]
            chosen = [e for e in events if _fields(selector, e)]
            return 200, {"kind": "EventList", "apiVersion": "v1", "metadata": {}, "items": chosen}
        if match := _PODS.match(path):
            namespace, name = match.groups()
            if name is None and method == "GET":
                return 200, self._list("PodList", "v1", self._in(self.pods, namespace), query)
            if name is not None and method == "GET":
                return self._log(namespace, name, query)
        return _status(404, "NotFound", f"the server could not find {method} {path}")

    def _post_job(self, namespace: str, body: Json) -> tuple[int, Any]:
        try:
            kubernetes_validate.validate(body, SCHEMA_VERSION, strict=True)
        except kubernetes_validate.ValidationError as exc:
            path = ".".join(str(p) for p in exc.path)
            return _status(422, "Invalid", f"Job.batch is invalid: {path}: {exc.message}")
        name = body["metadata"]["name"]
        if (namespace, name) in self.jobs:
            return _status(409, "AlreadyExists", f'jobs.batch "{name}" already exists')
        used = len(self._in(self.jobs, namespace))
        if self.job_quota is not None and used >= self.job_quota:
            message = (
                f'jobs.batch "{name}" is forbidden: exceeded quota: eval-quota, requested: '
                f"count/jobs.batch=1, used: count/jobs.batch={used}, "
                f"limited: count/jobs.batch={self.job_quota}"
            )
            return _status(403, "Forbidden", message)
        created = self._create_job(namespace, body)
        if self.on_create is not None:
            self.on_create(namespace, name)
        return 201, copy.deepcopy(created)

    def _post_secret(self, namespace: str, body: Json) -> tuple[int, Any]:
        try:
            kubernetes_validate.validate(body, SCHEMA_VERSION, strict=True)
        except kubernetes_validate.ValidationError as exc:
            path = ".".join(str(p) for p in exc.path)
            return _status(422, "Invalid", f"Secret is invalid: {path}: {exc.message}")
        name = body["metadata"]["name"]
        if (namespace, name) in self.secrets:
            return _status(409, "AlreadyExists", f'secrets "{name}" already exists')
        secret = copy.deepcopy(body)
        secret["metadata"].update(uid=str(uuid.uuid4()), creationTimestamp=self._now())
        secret["data"] = {
            k: base64.b64encode(v.encode()).decode() for k, v in secret.pop("stringData").items()
        }
        self.secrets[(namespace, name)] = secret
        return 201, secret

    def _finish_foreground(self, namespace: str, name: str) -> None:
        """The garbage collector ends a foreground deletion: the dependents that block their
        owner's deletion (`blockOwnerDeletion`) first, then the Job; the others are left for
        its next pass, as orphans (`collect_garbage`)."""
        job = self.jobs.pop((namespace, name))
        uid = job["metadata"]["uid"]
        for key, secret in list(self.secrets.items()):
            refs = secret["metadata"].get("ownerReferences") or []
            if any(r.get("uid") == uid and r.get("blockOwnerDeletion") for r in refs):
                del self.secrets[key]

    def _collect_forever(self) -> None:
        while not self._closed:
            time.sleep(self.gc_every)
            if not self.gc_paused:
                self.collect_garbage()

    def _quota_refusal(self, namespace: str, pod_spec: Json) -> str | None:
        """Why the quota refuses one more pod like `pod_spec` (`requested: ..., used: ...,
        limited: ...`, as the quota admission plugin says it), or None when it fits."""
        if self.pod_quota is not None and self._live_pods(namespace) >= self.pod_quota:
            used = self._live_pods(namespace)
            return f"requested: pods=1, used: pods={used}, limited: pods={self.pod_quota}"
        wanted = _pod_usage(self._admitted(pod_spec))
        used_now = self._compute_used(namespace)
        for resource, hard in sorted(self.compute_quota.items()):
            need, used = wanted.get(resource, Decimal(0)), used_now.get(resource, Decimal(0))
            if used + need > parse_quantity(hard):
                return (
                    f"requested: {resource}={_show(need)}, used: {resource}={_show(used)}, "
                    f"limited: {resource}={hard}"
                )
        return None

    def _quota_refused_pod(self, job: Json, refusal: str) -> None:
        meta = job["metadata"]
        message = (
            f'Error creating: pods "{meta["name"]}-{uuid.uuid4().hex[:5]}" is forbidden: '
            f"exceeded quota: eval-quota, {refusal}"
        )
        now = self._now()
        self.events.append(
            {
                "apiVersion": "v1",
                "kind": "Event",
                "metadata": {
                    "name": f"{meta['name']}.{uuid.uuid4().hex[:8]}",
                    "namespace": meta["namespace"],
                },
                "involvedObject": {
                    "apiVersion": "batch/v1",
                    "kind": "Job",
                    "name": meta["name"],
                    "namespace": meta["namespace"],
                    "uid": meta["uid"],
                },
                "type": "Warning",
                "reason": "FailedCreate",
                "message": message,
                "firstTimestamp": now,
                "lastTimestamp": now,
                "count": 1,
                "source": {"component": "job-controller"},
            }
        )

    def _create_job(self, namespace: str, job: Json) -> Json:
        meta = job["metadata"]
        uid = str(uuid.uuid4())
        meta.update(
            namespace=namespace,
            uid=uid,
            creationTimestamp=self._now(),
            generation=1,
        )
        controller = {"batch.kubernetes.io/controller-uid": uid, "controller-uid": uid}
        names = {"batch.kubernetes.io/job-name": meta["name"], "job-name": meta["name"]}
        template_meta = job["spec"]["template"].setdefault("metadata", {})
        template_meta.setdefault("labels", {}).update(controller | names)
        job["spec"]["selector"] = {"matchLabels": {"batch.kubernetes.io/controller-uid": uid}}
        job["status"] = {}
        if not job["spec"].get("suspend"):
            # The controller's first sync of the Job ("Job first start" in `syncJob`): its
            # deadline counts from here, scheduling and image pulls included.
            job["status"]["startTime"] = self._now()
        self.jobs[(namespace, meta["name"])] = job
        return job

    def _delete_job(
        self, namespace: str, name: str, query: dict[str, list[str]], body: Any
    ) -> tuple[int, Any]:
        job = self.jobs.get((namespace, name))
        if job is None:
            return _status(404, "NotFound", f'jobs.batch "{name}" not found')
        policy = (body or {}).get("propagationPolicy") or query.get("propagationPolicy", [None])[0]
        self.deletions.append((name, policy))
        if policy in ("Foreground", "Background"):
            for pod in self._pods_of(namespace, name):
                del self.pods[(namespace, pod["metadata"]["name"])]
        if policy == "Foreground":
            job["metadata"].update(deletionTimestamp=self._now(), finalizers=["foregroundDeletion"])
            answer = copy.deepcopy(job)
            if not self.hold_deletions and not self.gc_paused:
                self._finish_foreground(namespace, name)  # the collector's pass, at once
            return 200, answer  # the object, still present: not a Status
        del self.jobs[(namespace, name)]  # its dependents go on the collector's next pass...
        if policy != "Background":  # ...but without a policy, batch/v1 orphans them
            uid = job["metadata"]["uid"]
            for secret in self.secrets.values():
                refs = secret["metadata"].get("ownerReferences") or []
                secret["metadata"]["ownerReferences"] = [r for r in refs if r["uid"] != uid]
        return 200, {"kind": "Status", "apiVersion": "v1", "status": "Success", "metadata": {}}

    def _log(self, namespace: str, name: str, query: dict[str, list[str]]) -> tuple[int, Any]:
        pod = self.pods.get((namespace, name))
        if pod is None:
            return _status(404, "NotFound", f'pods "{name}" not found')
        spec = pod["spec"]
        names = [c["name"] for c in spec["containers"] + spec.get("initContainers", [])]
        container = query.get("container", [""])[0]
        if container not in names:
            return _status(400, "BadRequest", f"container {container} is not valid for pod {name}")
        if pod["status"]["phase"] == "Pending":
            message = f'container "{container}" in pod "{name}" is waiting to start'
            return _status(400, "BadRequest", message)
        if (namespace, name) in self._unreachable:
            url = f"https://10.0.3.7:10250/containerLogs/{namespace}/{name}/{container}"
            message = f'Get "{url}": dial tcp 10.0.3.7:10250: connect: no route to host'
            return _status(500, "InternalError", message)
        text = self.logs.get((namespace, name, container), "")
        tail = query.get("tailLines", [None])[0]
        if tail is not None:
            text = "".join(text.splitlines(keepends=True)[-int(tail) :])
        answer = _Text(text)
        limit = query.get("limitBytes", [None])[0]
        answer.limit = int(limit) if limit is not None else None
        return 200, answer

    def _list(
        self, kind: str, api_version: str, objects: list[Json], query: dict[str, list[str]]
    ) -> Json:
        selector = query.get("labelSelector", [""])[0]
        matching = [o for o in objects if _selects(selector, o["metadata"].get("labels") or {})]
        start = int(query.get("continue", ["0"])[0])
        limit = int(query.get("limit", [str(len(matching) or 1)])[0])
        page = matching[start : start + limit]
        meta: Json = {"resourceVersion": str(self._version)}
        if start + limit < len(matching):
            meta["continue"] = str(start + limit)
        return {"kind": kind, "apiVersion": api_version, "metadata": meta, "items": page}

    # Helpers.

    def _live_pods(self, namespace: str) -> int:
        """Pods a quota counts: those not yet Succeeded or Failed."""
        pods = self._in(self.pods, namespace)
        return sum(1 for p in pods if (p.get("status") or {}).get("phase") not in _TERMINAL)

    def _admitted(self, pod_spec: Json) -> Json:
        """The pod's spec as admission leaves it: the RuntimeClass admission plugin sets its
        class's overhead (`setOverhead` in plugin/pkg/admission/runtimeclass/admission.go)."""
        overhead = self.runtime_classes.get(pod_spec.get("runtimeClassName") or "")
        return pod_spec | {"overhead": dict(overhead)} if overhead else pod_spec

    def _compute_used(self, namespace: str) -> dict[str, Decimal]:
        """What the live pods use of the compute resources, as the quota controller counts."""
        used: dict[str, Decimal] = {}
        for pod in self._in(self.pods, namespace):
            if (pod.get("status") or {}).get("phase") in _TERMINAL:
                continue
            for resource, value in _pod_usage(pod.get("spec") or {}).items():
                used[resource] = used.get(resource, Decimal(0)) + value
        return used

    def _quotas(self, namespace: str) -> list[Json]:
        """`eval-quota` as the quota controller reports it, when the test set one."""
        hard: Json = {}
        used: Json = {}
        if self.compute_quota:
            counted = self._compute_used(namespace)
            hard |= self.compute_quota
            used |= {r: _show(counted.get(r, Decimal(0))) for r in self.compute_quota}
        if self.pod_quota is not None:
            hard["pods"], used["pods"] = str(self.pod_quota), str(self._live_pods(namespace))
        if self.job_quota is not None:
            hard["count/jobs.batch"] = str(self.job_quota)
            used["count/jobs.batch"] = str(len(self._in(self.jobs, namespace)))
        if not hard:
            return []
        meta = {"name": "eval-quota", "namespace": namespace}
        return [
            {
                "kind": "ResourceQuota",
                "apiVersion": "v1",
                "metadata": meta,
                "spec": {"hard": dict(hard)},
                "status": {"hard": hard, "used": used},
            }
        ]

    def _take_fault(self, method: str, path: str) -> Fault | None:
        for i, fault in enumerate(self.faults):
            if fault.method == method and fault.path_part in path:
                return self.faults.pop(i)
        return None

    def _now(self) -> str:
        return self.clock.stamp()

    @staticmethod
    def _in(store: dict[tuple[str, str], Json], namespace: str) -> list[Json]:
        return [obj for (ns, _), obj in sorted(store.items()) if ns == namespace]

    def _pods_of(self, namespace: str, name: str) -> list[Json]:
        return [
            pod
            for (ns, _), pod in self.pods.items()
            if ns == namespace and pod["metadata"]["labels"].get("job-name") == name
        ]

    def _add_pod(self, job: Json, index: int, *, ready: bool) -> str:
        namespace, job_name = job["metadata"]["namespace"], job["metadata"]["name"]
        template = copy.deepcopy(job["spec"]["template"])
        name = f"{job_name}-{index}-{uuid.uuid4().hex[:5]}"
        labels = template["metadata"]["labels"]
        annotations = {}
        if job["spec"].get("completionMode") == "Indexed":
            labels[INDEX_LABEL] = str(index)
            annotations[INDEX_LABEL] = str(index)
        owner = {"apiVersion": "batch/v1", "kind": "Job", "name": job_name, "controller": True}
        template["spec"] = self._admitted(template["spec"])
        self.pods[(namespace, name)] = {
            "apiVersion": "v1",
            "kind": "Pod",
            "metadata": {
                "name": name,
                "namespace": namespace,
                "uid": str(uuid.uuid4()),
                "labels": labels,
                "annotations": annotations,
                "creationTimestamp": self._now(),
                "ownerReferences": [owner | {"uid": job["metadata"]["uid"]}],
            },
            "spec": template["spec"],
            "status": {"phase": "Pending"},
        }
        if ready:
            self._start_containers(self.pods[(namespace, name)])
        return name

    def _start_containers(self, pod: Json) -> None:
        """The kubelet pulled both images and started the policy sidecar, then the evaluator."""
        spec, now = pod["spec"], self._now()

        def running(container: Json) -> Json:
            return {
                "name": container["name"],
                "image": container["image"],
                "imageID": "",
                "ready": True,
                "restartCount": 0,
                "started": True,
                "state": {"running": {"startedAt": now}},
            }

        pod["status"] = {
            "phase": "Running",
            "initContainerStatuses": [running(c) for c in spec.get("initContainers", [])],
            "containerStatuses": [running(c) for c in spec["containers"]],
        }

    def _evaluator_exits(self, pod: Json, code: int, *, oom: bool = False) -> None:
        """The evaluator exits with `code`; the kubelet then stops the policy sidecar (sidecars
        end after the main containers, KEP-753: pkg/kubelet/kuberuntime's termination order).
        Its SIGTERM does nothing to a `python3` running as PID 1 without a handler, so the
        kubelet kills it after the grace period: the sidecar's state reads exit code 137,
        while a crash or OOM kill it had before stays in its lastState."""
        now = self._now()
        for status in pod["status"].get("containerStatuses", []):
            if status["name"] == EVALUATOR:
                status.update(ready=False, started=False)
                status["state"] = {
                    "terminated": {
                        "exitCode": code,
                        "reason": "OOMKilled" if oom else "Completed" if code == 0 else "Error",
                        "finishedAt": now,
                    }
                }
        for status in pod["status"].get("initContainerStatuses", []):
            if status["name"] == "policy":
                status.update(ready=False, started=False)
                status["state"] = {
                    "terminated": {"exitCode": 137, "reason": "Error", "finishedAt": now}
                }

    def _conclude(self, job: Json, interim: str, final: str, reason: str, message: str) -> None:
        """The Job's end, in the controller's order (`controller`): under 1.31 the terminal
        condition waits for `settle`."""
        now = self._now()
        job["status"]["conditions"] = [
            {
                "type": kind,
                "status": "True",
                "reason": reason,
                "message": message,
                "lastProbeTime": now,
                "lastTransitionTime": now,
            }
            for kind in self._conditions(interim, final, reason)
        ]

    def _conditions(self, interim: str, final: str, reason: str) -> tuple[str, ...]:
        if self.controller == "1.31":
            return (interim,)
        return (interim, final) if reason == "PodFailurePolicy" else (final,)

    def _end_pod(self, pod: Json) -> None:
        """The controller deletes a running pod: gone at once under 1.29; under 1.31 it stays
        terminating (deletionTimestamp set, the job-tracking finalizer on) until `settle`."""
        meta = pod["metadata"]
        if self.controller == "1.31":
            meta.update(
                deletionTimestamp=self._now(),
                finalizers=["batch.kubernetes.io/job-tracking"],
            )
        else:
            del self.pods[(meta["namespace"], meta["name"])]


class _Server(ThreadingHTTPServer):
    request_queue_size = 1024  # many clients connecting at once wait, as on a real server


class _Text(str):
    """A plain-text answer (pod logs), cut at `limit` bytes (limitBytes) when set."""

    limit: int | None = None


class _Handler(BaseHTTPRequestHandler):
    server_double: ApiServerDouble

    def log_message(self, format: str, *args: Any) -> None:  # quiet
        pass

    def _serve(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(length) if length else b""
        body = json.loads(raw) if raw else None
        (status, payload), retry_after = self.server_double.handle(self.command, self.path, body)
        if isinstance(payload, WatchRequest):
            self._stream(payload)
            return
        if isinstance(payload, _Text):  # lone surrogates stand for bytes that are not UTF-8
            data, kind = payload.encode("utf-8", "surrogateescape"), "text/plain; charset=utf-8"
            data = data[: payload.limit] if payload.limit is not None else data
        else:
            data, kind = json.dumps(payload).encode(), "application/json"
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        if retry_after is not None:
            self.send_header("Retry-After", str(retry_after))
        self.end_headers()
        self.wfile.write(data)

    def _stream(self, watch: WatchRequest) -> None:
        """A watch: events as JSON lines in HTTP/1.1 chunks (as the real server sends them;
        a client reads each chunk as it comes), the connection closed at the end."""
        self.protocol_version = "HTTP/1.1"
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Transfer-Encoding", "chunked")
        self.send_header("Connection", "close")
        self.end_headers()

        def send(event: Json) -> None:
            line = json.dumps(event).encode() + b"\n"
            self.wfile.write(b"%x\r\n%s\r\n" % (len(line), line))
            self.wfile.flush()

        try:
            self.server_double.stream(watch, send)
            self.wfile.write(b"0\r\n\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client went away (it stopped watching)
        self.close_connection = True

    do_GET = do_POST = do_DELETE = _serve


def _pod_usage(pod_spec: Json) -> dict[str, Decimal]:
    """What a pod takes from a quota's compute resources: its containers' requests and limits
    (the policy sidecar's as well: restartable init containers run beside the others) plus its
    overhead, in both (`PodUsageFunc` in pkg/quota/v1/evaluator/core/pods.go, through
    `PodRequests` and `PodLimits` of component-helpers/resource/helpers.go); `cpu` and
    `memory` alone mean the requests."""
    usage: dict[str, Decimal] = {}
    containers = [*pod_spec.get("initContainers", []), *pod_spec.get("containers", [])]
    overhead = pod_spec.get("overhead") or {}
    for kind in ("requests", "limits"):
        amounts = [(c.get("resources") or {}).get(kind) or {} for c in containers]
        for name, value in [(n, v) for a in [*amounts, overhead] for n, v in a.items()]:
            key = f"{kind}.{name}"
            usage[key] = usage.get(key, Decimal(0)) + parse_quantity(value)
    for name in ("cpu", "memory"):
        usage[name] = usage.get(f"requests.{name}", Decimal(0))
    return usage


def _show(value: Decimal) -> str:
    return f"{value.normalize():f}"


def _indexes(job: Json) -> range:
    spec = job["spec"]
    return range(spec.get("completions", 1) if spec.get("completionMode") == "Indexed" else 1)


def _status(code: int, reason: str, message: str) -> tuple[int, Json]:
    return code, {
        "kind": "Status",
        "apiVersion": "v1",
        "metadata": {},
        "status": "Failure",
        "message": message,
        "reason": reason,
        "code": code,
    }


def _job_of(pod: Json) -> str | None:
    """The name of the Job a pod belongs to (the controller's label)."""
    return ((pod.get("metadata") or {}).get("labels") or {}).get("job-name")


def _gone(version: str) -> Json:
    """The ERROR event a real API server sends when a watch's version was compacted away."""
    message = f"too old resource version: {version}"
    return {"type": "ERROR", "object": _status(410, "Expired", message)[1]}


def _kind_of(request: Recorded) -> str:
    """`verb resource` of a recorded request, as RBAC would name it."""
    parts = request.path.rstrip("/").split("/")
    resource = parts[-1]
    if resource == "log":
        return "get pods/log"
    collection = resource in ("jobs", "pods", "events", "secrets", "resourcequotas")
    if not collection:
        resource = parts[-2]
    if request.method == "POST":
        return f"create {resource}"
    if request.method == "DELETE":
        return f"delete {resource}"
    if not collection:
        return f"get {resource}"
    watching = request.query.get("watch", [""])[0] in _WATCHING
    return f"{'watch' if watching else 'list'} {resource}"


def _error(code: int) -> tuple[int, Json]:
    reasons = {
        410: "Expired",
        429: "TooManyRequests",
        500: "InternalError",
        503: "ServiceUnavailable",
    }
    return _status(code, reasons.get(code, "Failure"), f"injected fault {code}")


def _fields(selector: str, obj: Json) -> bool:
    """Field selectors of equality requirements on dotted paths (`involvedObject.name=x`)."""
    for requirement in filter(None, (r.strip() for r in selector.split(","))):
        path, value = requirement.replace("==", "=").split("=", 1)
        current: Any = obj
        for part in path.split("."):
            current = current.get(part) if isinstance(current, dict) else None
        if current != value:
            return False
    return True


def _selects(selector: str, labels: dict[str, str]) -> bool:
    """Equality (`k=v`, `k==v`), inequality (`k!=v`) and existence (`k`) requirements."""
    for requirement in filter(None, (r.strip() for r in selector.split(","))):
        if "!=" in requirement:
            key, value = requirement.split("!=", 1)
            if labels.get(key) == value:
                return False
        elif "=" in requirement:
            key, value = requirement.replace("==", "=").split("=", 1)
            if labels.get(key) != value:
                return False
        elif requirement not in labels:
            return False
    return True


@contextmanager
def running_apiserver(
    controller: Controller = "1.31", *, clock: ClusterClock | None = None
) -> Iterator[ApiServerDouble]:
    """A started double, shut down afterwards (wrap it in a fixture), its Job controller
    ending Jobs as `controller`'s does, on `clock` (a fresh one by default)."""
    with ApiServerDouble(controller=controller, clock=clock or ClusterClock()) as double:
        yield double


def executor_for(
    double: ApiServerDouble, *, sleeps: list[float] | None = None, attempts: int = 6
) -> KubernetesExecutor:
    """An executor whose official client talks to `double`; waits are recorded, not slept."""
    configuration = no_client_retries(Configuration(host=double.host))
    recorded = sleeps if sleeps is not None else []
    return KubernetesExecutor(
        ApiClient(configuration),
        namespace=NAMESPACE,
        backoff=Backoff(attempts=attempts, base_s=0.5, cap_s=8.0),
        sleep=recorded.append,
        jitter=lambda: 0.5,
    )


def collect_logs(
    executor: KubernetesExecutor,
    submission_id: int,
    attempt: int,
    *,
    container: str = EVALUATOR,
    tail_lines: int = 0,
) -> list[str]:
    """One container's log per shard index of the attempt's Job, its shards read from the Job
    ("" where no pod is left); the evaluator's by default."""
    job = executor.batch.read_namespaced_job(job_name(submission_id, attempt), executor.namespace)
    spec = job.spec
    indexed = spec is not None and spec.completion_mode == "Indexed"
    shards = (spec.completions or 1) if spec is not None and indexed else 1
    pods = executor.job_pods(submission_id, attempt)
    return executor.logs(pods, shards, container=container, tail_lines=tail_lines)
