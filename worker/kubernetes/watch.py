"""Run one attempt as a Kubernetes Job and follow it to a final state.

The worker builds the Job (`worker.kubernetes.manifest.build_job`) and waits, beating, until
the namespace's ResourceQuotas have room for all of it (`worker.kubernetes.quota`), so workers
that outnumber the quota (a rollout) never create Jobs the quota would starve. It creates the
Job (adopting it on 409), then follows it through the process's watch of the cluster
(`worker.kubernetes.informer`: one list+watch of Jobs and one of pods for every attempt the
process follows). It looks whenever the Job or its pods change, and every `k8s_poll_interval`
seconds for its clocks: the pods say when a container can never start, and when the cluster,
not the policy, stopped the evaluation (`pod_history`); the Job's end decides the attempt's
(`ended_job`). Progress is the evaluator's log, read every `k8s_progress_interval` seconds
while it runs. Between looks the worker asks the server every second whether the attempt still
runs: a cancel deletes the Job at once, and the evaluator, on SIGTERM, stops.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from kubernetes.client import V1Pod

from evaluator.plan import EvaluationPlan
from internal_api.schemas import Assignment, ErrorCause, FinalReport, ReportOut, State
from worker.kubernetes.client import (
    JobConflict,
    KubernetesError,
    KubernetesExecutor,
    kubernetes_executor,
)
from worker.kubernetes.ended_job import final_report
from worker.kubernetes.informer import ClusterWatch, Failure, cluster_watch
from worker.kubernetes.manifest import EVALUATOR, JobSpec, build_job, job_name
from worker.kubernetes.pod_history import PodHistory
from worker.kubernetes.quota import demand, never_fits, shortfall
from worker.kubernetes.spec import EvaluatorImageNotAllowed, job_spec
from worker.kubernetes.status import JobStatus, job_status, pod_view, progress_in
from worker.outcome import ended
from worker.server_api import ServerAPI, ServerUnavailable
from worker.settings import WorkerSettings

log = logging.getLogger(__name__)

JOB_DEADLINE_GRACE_S = 300.0
"""Beyond the Job's activeDeadlineSeconds (Kubernetes stops it there), before the reconciler
times the attempt out: time to see the Job end and report it."""
API_OUTAGE_S = 600.0  # the API server unreachable this long: the attempt ends `error`
CANCEL_CHECK_S = 1.0  # between looks, a heartbeat this often: a cancel stops the Job at once
CLUSTER = ErrorCause.CLUSTER
CONFIGURATION = ErrorCause.CONFIGURATION
_ROOM = object()  # `_until_room`'s answer when the Job may be created
_UNKNOWN = object()  # ... when the quotas could not be read: the API server decides at creation


class _Going:
    """A look's answer when the Job runs on."""


GOING = _Going()


def run_as_job(
    api: ServerAPI,
    settings: WorkerSettings,
    handed: Assignment,
    *,
    stop: threading.Event | None = None,
) -> State | None:
    """Run a claimed (`launching`) attempt as a Job; returns the state it ended in. `stop`
    (tests, shutdown) ends the watch early and leaves the Job to the reconciler."""
    try:
        watch = _watch_for(api, settings, handed, stop)
    except Exception as exc:  # our configuration: error, with the reason
        return api.final(handed.submission_id, handed.attempt, _unrunnable(exc))
    return _guarded(watch, watch.run)


def resume_watch(
    api: ServerAPI,
    settings: WorkerSettings,
    submission_id: int,
    attempt: int,
    *,
    stop: threading.Event | None = None,
) -> State | None:
    """Watch the Job of a `running` attempt whose watcher was lost (a worker killed): the
    reconciler asks for this when the Job still exists, so the evaluation is not thrown away."""
    handed = api.assignment(submission_id, attempt)
    if handed is None:
        return None  # ended or replaced meanwhile: nothing to watch
    try:
        watch = _watch_for(api, settings, handed, stop)
    except Exception as exc:
        return api.final(submission_id, attempt, _unrunnable(exc))
    log.info("resuming the watch of Job %s", watch.spec.name)
    return _guarded(watch, watch.resume)


def _unrunnable(exc: Exception) -> FinalReport:
    """`error` for an attempt the worker cannot make a Job of; an evaluator image the operator
    has not allowed is the configuration's cause (no quota, not run again by itself)."""
    cause = CONFIGURATION if isinstance(exc, EvaluatorImageNotAllowed) else None
    return ended(State.ERROR, f"cannot run: {exc}", cause=cause)


def _watch_for(
    api: ServerAPI, settings: WorkerSettings, handed: Assignment, stop: threading.Event | None
) -> _Watch:
    spec = job_spec(settings, handed)
    executor = kubernetes_executor(settings)
    pods = PodHistory(spec.shards, settings.k8s_pending_timeout_s)
    return _Watch(api, settings, executor, spec, handed.plan, stop or threading.Event(), pods)


def _guarded(watch: _Watch, body: Callable[[], State | None]) -> State | None:
    try:
        return body()
    except Exception as exc:  # a bug of ours: still a final state with a reason, and no Job
        log.exception("watching Job %s failed", watch.spec.name)
        return watch.end(State.ERROR, f"the worker failed: {type(exc).__name__}: {exc}")
    finally:
        watch.executor.close()


@dataclass
class _Watch:
    api: ServerAPI
    settings: WorkerSettings
    executor: KubernetesExecutor
    spec: JobSpec
    plan: EvaluationPlan
    stop: threading.Event
    pods: PodHistory
    _read_progress: dict[str, Any] = field(default_factory=dict)
    _progress_at: float | None = None
    """When the log was last read for progress (first: when the evaluator was seen started)."""
    _room_checked_at: float = -1e9
    _outage_since: float | None = None
    _state: State | None = None
    _uid: str = ""
    """The uid of the Job this watch created (empty when it resumed someone else's watch)."""
    _quotas_read: bool = False
    """Whether the quotas could be read: only then can a refusal be waited out."""

    @property
    def ids(self) -> tuple[int, int]:
        return self.spec.submission_id, self.spec.attempt

    def run(self) -> State | None:
        room = self._until_room()
        if room not in (_ROOM, _UNKNOWN):
            return room  # type: ignore[return-value]
        running = self._running()
        if running is None or not running.applied:
            return running.state if running is not None else None
        while True:
            try:
                started = self.executor.start(self.spec)
                break
            except JobConflict as exc:  # not ours to delete: another deployment's, or deleting
                reason = f"cannot create the evaluation Job: {exc}"
                return self._report(ended(State.ERROR, reason))
            except KubernetesError as exc:
                if exc.status == 403 and "exceeded quota" in str(exc) and room is _ROOM:
                    # Another worker took the room between our look and our create.
                    room = self._until_room()
                    if room in (_ROOM, _UNKNOWN):
                        continue
                    return room  # type: ignore[return-value]
                reason = f"cannot create the evaluation Job: {exc}"
                return self.end(State.ERROR, reason, cause=CLUSTER)
        if started.adopted:
            log.info("adopted the existing Job %s", started.name)
        self._uid, self._quotas_read = started.uid, room is _ROOM
        return self.follow()

    def _running(self) -> ReportOut | None:
        """`running`, with the deadline of a Job made now: its own, and time to see it end."""
        deadline_s = self.spec.active_deadline_seconds + JOB_DEADLINE_GRACE_S
        reason = f"evaluating as Kubernetes Job {self.spec.name}"
        return self.api.running(*self.ids, reason=reason, deadline_s=deadline_s)

    def _until_room(self) -> object:
        """Wait until the namespace's quotas have room for the whole Job, beating meanwhile:
        `_ROOM`, `_UNKNOWN` (the quotas cannot be read), or the state the attempt ended in
        (cancelled, or a quota it can never fit)."""
        needs = demand(build_job(self.spec), overhead=self.settings.k8s_runtime_overhead)
        waiting = False
        while True:
            try:
                quotas = self.executor.quotas()
            except KubernetesError as exc:  # the quota still decides at creation
                log.warning("Job %s: the quotas could not be read: %s", self.spec.name, exc)
                return _UNKNOWN
            never = never_fits(quotas, needs)
            if never is not None:
                return self.end(State.ERROR, f"cannot run on this cluster: {never}")
            short = shortfall(quotas, needs)
            if short is None:
                return _ROOM
            if not waiting:
                log.info("Job %s waits for room: %s", self.spec.name, short)
                waiting = True
            if not self._beat({"phase": "waiting for room in the cluster", "detail": short}):
                return self._cancelled()
            if self.stop.wait(self.settings.k8s_poll_interval):
                return None  # stopped: the claim is left to the reconciler

    def resume(self) -> State | None:
        """Follow a Job whose watcher was lost, giving it its Secret if that died with it."""
        try:
            self.executor.give_evaluation(self.spec)
        except KubernetesError as exc:  # gone (the next look says so) or the API: look anyway
            log.warning("Job %s: its evaluation Secret: %s", self.spec.name, exc)
        return self.follow()

    def follow(self) -> State | None:
        """Follow the Job until it ends (or the attempt ends elsewhere): a look whenever the
        Job or its pods change, and every `k8s_poll_interval` for the clocks (pending
        timeout, progress); a heartbeat every `CANCEL_CHECK_S` between."""
        with cluster_watch(self.settings) as cluster:
            changed = cluster.subscribe(self.spec.name)
            try:
                return self._follow(cluster, changed)
            finally:
                cluster.unsubscribe(self.spec.name, changed)

    def _follow(self, cluster: ClusterWatch, changed: threading.Event) -> State | None:
        every = self.settings.k8s_poll_interval
        next_look = next_beat = time.monotonic()
        while not self.stop.is_set():
            now = time.monotonic()
            if changed.is_set() or now >= next_look:
                changed.clear()
                next_look, next_beat = now + every, now + CANCEL_CHECK_S
                ended = self._look_at(cluster)
                if not isinstance(ended, _Going):
                    return ended
            elif now >= next_beat:
                next_beat = now + CANCEL_CHECK_S
                if not self._beat(None):  # only asks whether the attempt still runs
                    return self._cancelled()
            wait = min(next_look, next_beat) - time.monotonic()
            changed.wait(max(0.0, min(wait, CANCEL_CHECK_S)))
        return None  # stopped: the Job runs on, and the reconciler hands it to a new watcher

    def _look_at(self, cluster: ClusterWatch) -> State | _Going | None:
        """One look at what the watch knows of the Job (a request only to confirm a Job the
        watch has not seen, and for the log when progress is due)."""
        failure = cluster.failing()
        if failure is not None:
            return self._outage(failure)
        if not cluster.synced:
            return GOING  # its first list is under way; it wakes us when done
        job = cluster.job(self.spec.name)
        try:
            # Not (yet) in the watch's cache: created a moment ago, or gone. Ask.
            status = job_status(job) if job is not None else self.executor.status(*self.ids)
            if status.phase not in ("pending", "running"):
                return self._finish(final_report(self.executor, self.spec, self.plan, status))
            ended = self._look(status, cluster.pods_of(self.spec.name))
        except KubernetesError as exc:
            now = time.monotonic()
            self._outage_since = self._outage_since if self._outage_since is not None else now
            return self._outage(Failure(self._outage_since, str(exc)))
        self._outage_since = None
        return GOING if ended is None else ended

    def _outage(self, failure: Failure) -> State | _Going | None:
        log.warning("Job %s: the API server failed: %s", self.spec.name, failure.error)
        if time.monotonic() - failure.since > API_OUTAGE_S:
            reason = f"the Kubernetes API failed for too long: {failure.error}"
            return self.end(State.ERROR, reason)
        if not self._beat({"phase": "unknown"}):
            return self._cancelled()
        return GOING

    def _look(self, status: JobStatus, pods: list[V1Pod]) -> State | None:
        """One look at a live Job: stuck pods end it, else report progress (the heartbeat)."""
        view = pod_view(pods)
        taken = self._quotas_read and self._uid and view.count < self.spec.shards
        if taken and self._room_taken():
            return self._make_room()
        if view.stuck is not None:
            return self.end(State.ERROR, f"the evaluation could not start: {view.stuck}")
        verdict = self.pods.stopped(view, self._job_runs, self._warnings)
        if verdict is not None:
            return self.end(State.ERROR, verdict.reason, cause=verdict.cause)
        progress: dict[str, Any] = {"phase": status.phase, "done": 0}
        if view.evaluating:
            now = time.monotonic()
            if self._progress_at is None:
                self._progress_at = now  # its log says little yet
            elif now - self._progress_at >= self.settings.k8s_progress_interval:
                self._progress_at = now
                self._read_progress = self._progress(pods)
            progress |= self._read_progress
        if not self._beat(progress):
            return self._cancelled()
        return None

    def _job_runs(self) -> bool:
        return self.executor.status(*self.ids).phase in ("pending", "running")

    def _room_taken(self) -> bool:
        """Whether the quota refused this Job's pods: another worker took the room between
        our look at the quotas and our Job's creation. Asked at most every poll interval."""
        now = time.monotonic()
        if now - self._room_checked_at < self.settings.k8s_poll_interval:
            return False
        self._room_checked_at = now
        try:
            warnings = self.executor.events(*self.ids, uid=self._uid)
        except KubernetesError as exc:
            log.warning("Job %s: its events could not be read: %s", self.spec.name, exc)
            return False
        return any("exceeded quota" in w for w in warnings)

    def _make_room(self) -> State | None:
        """Take the Job back and make it again once the quotas have room, so that its pods
        do not wait on the Job controller while its deadline runs. None: follow it again."""
        log.info("Job %s: the quota refused its pods; waiting for room", self.spec.name)
        self._delete()
        progress = {"phase": "waiting for room in the cluster", "detail": "the quota is full"}
        while self.executor.status(*self.ids).phase != "missing":  # its foreground deletion
            if not self._beat(dict(progress)):
                return self._cancelled()
            if self.stop.wait(min(CANCEL_CHECK_S, self.settings.k8s_poll_interval)):
                return None
        room = self._until_room()
        if room not in (_ROOM, _UNKNOWN):
            return room  # type: ignore[return-value]
        try:
            started = self.executor.start(self.spec)
        except KubernetesError as exc:
            reason = f"cannot create the evaluation Job again: {exc}"
            return self.end(State.ERROR, reason, cause=CLUSTER)
        self._uid = started.uid
        self.pods.forget()
        self._quotas_read = room is _ROOM
        running = self._running()  # the new Job's clock starts now, and so does the attempt's
        if running is None or not running.applied:  # ended or replaced meanwhile
            self._delete()
            return running.state if running is not None else State.CANCELLED
        return None

    def _warnings(self) -> str:
        try:
            warnings = self.executor.events(*self.ids)
        except KubernetesError as exc:
            log.warning("Job %s: its events could not be read: %s", self.spec.name, exc)
            return ""
        return f": {warnings[-1]}" if warnings else ""

    def _progress(self, pods: list[V1Pod]) -> dict[str, Any]:
        """Progress from the evaluators' logs so far (the last read's, if this one fails)."""
        try:
            logs = self.executor.logs(pods, self.spec.shards, container=EVALUATOR)
        except KubernetesError as exc:
            log.warning("Job %s: its log could not be read: %s", self.spec.name, exc)
            return self._read_progress
        return progress_in(logs, self.plan)

    def _beat(self, progress: dict[str, Any] | None) -> bool:
        """Report progress (None: a heartbeat only); False when the attempt ended elsewhere
        (its state is kept)."""
        if progress is not None:
            progress.setdefault("total", self.plan.episode_count())
        try:
            out = self.api.progress(*self.ids, progress)
        except ServerUnavailable as exc:  # the next look tries again; the Job runs on
            log.warning("Job %s: progress not delivered: %s", self.spec.name, exc)
            return True
        self._state = out.state
        return out.applied

    def end(self, state: State, reason: str, *, cause: ErrorCause | None = None) -> State | None:
        return self._finish(ended(state, reason, cause=cause))

    def _finish(self, report: FinalReport) -> State | None:
        """Report the attempt's end, then delete its Job."""
        log.info("Job %s: %s: %s", self.spec.name, report.state.value, report.reason)
        final = self._report(report)
        self._delete()
        return final

    def _report(self, report: FinalReport) -> State | None:
        return self.api.final(*self.ids, report)

    def _cancelled(self) -> State | None:
        """The attempt ended elsewhere (cancel, the reconciler): its Job goes too."""
        self._delete()
        return self._state

    def _delete(self) -> None:
        try:
            self.executor.cancel(*self.ids)
        except KubernetesError as exc:  # the reconciler deletes it on its next pass
            log.warning("could not delete Job %s: %s", job_name(*self.ids), exc)
