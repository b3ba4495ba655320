"""Run one attempt as a Kubernetes Job and watch it to a final state.

The worker builds the Job (`worker.kubernetes.manifest.build_job`), creates it (adopting it on
409), then looks every `k8s_poll_interval` seconds: the Job's conditions decide the end, the
pods say when an image cannot be pulled (no point waiting for the deadline), and the
evaluator's log gives the progress. Each look is also the attempt's heartbeat; when the server
says the attempt is no longer running (cancelled, timed out by the reconciler) the Job is
deleted. The result is read from the evaluator's log by this process: nothing in the pod can
write one.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from evaluator.job import JobOutputError, evaluation_job, result_from_logs
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.sources import LOG_TAIL_BYTES
from evaluator.suite import Suite
from server.kit.settings import Settings
from server.models import State, Submission, utcnow
from server.submissions.reports import report_progress
from worker.kubernetes.client import JobConflict, JobStatus, KubernetesError, KubernetesExecutor
from worker.kubernetes.manifest import (
    EVALUATOR,
    POLICY,
    JobSpec,
    Resources,
    active_deadline_for,
    job_name,
    needs_gpu,
)
from worker.outcome import conclude, final_state, finish, start_running

log = logging.getLogger(__name__)

DEADLINE_GRACE_S = 300.0  # beyond the Job's own deadline, before the reconciler times it out
API_OUTAGE_S = 600.0  # the API server unreachable this long: the attempt ends `error`
POLICY_LOG_LINES = 400
PROGRESS_EVERY = 3  # looks per read of the evaluator's log (each look is 2 API requests)
_EPISODE_LINE = re.compile(r"^manieval: run (\d+) episode \d+:", re.MULTILINE)


def kubernetes_executor(settings: Settings) -> KubernetesExecutor:
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
    return KubernetesExecutor(ApiClient(configuration), settings.k8s_namespace)


def job_spec(
    settings: Settings,
    submission_id: int,
    attempt: int,
    plan: EvaluationPlan,
    *,
    suite: Suite,
    suite_yaml: str,
    pinned: str,
) -> JobSpec:
    """The Job of this attempt, from the plan and the worker's settings (ValueError if bad)."""
    if not settings.evaluator_image:
        raise ValueError("no evaluator image is configured (MANIEVAL_EVALUATOR_IMAGE)")
    return JobSpec(
        submission_id=submission_id,
        attempt=attempt,
        namespace=settings.k8s_namespace,
        evaluator_image=settings.evaluator_image,
        policy_image=pinned,
        evaluation=evaluation_job(plan, suite_yaml=suite_yaml),
        evaluator_resources=Resources(settings.evaluator_cpu, settings.evaluator_memory, "2Gi"),
        policy_resources=Resources(
            cpu=f"{round(settings.policy_cpus * 1000)}m",
            memory=f"{settings.policy_memory_mib}Mi",
            ephemeral_storage="1Gi",
        ),
        gpu=needs_gpu(plan),
        active_deadline_seconds=active_deadline_for(plan.limits),
        runtime_class_name=settings.k8s_runtime_class,
        shards=min(suite.shards, plan.episode_count()),
    )


def run_as_job(
    sessions: sessionmaker[Session],
    settings: Settings,
    submission_id: int,
    attempt: int,
    *,
    suite: Suite,
    suite_yaml: str,
    phase: str,
    pinned: str,
    stop: threading.Event | None = None,
) -> State | None:
    """Run a claimed (`launching`) attempt as a Job; returns the state it ended in. `stop`
    (tests, shutdown) ends the watch early and leaves the Job to the reconciler."""
    try:
        watch = _watch_for(
            sessions, settings, submission_id, attempt, suite, suite_yaml, phase, pinned, stop
        )
    except Exception as exc:  # our configuration: error, with the reason
        return finish(sessions, submission_id, attempt, State.ERROR, f"cannot run: {exc}")
    return _guarded(watch, watch.run)


def resume_watch(
    sessions: sessionmaker[Session],
    settings: Settings,
    submission_id: int,
    attempt: int,
    *,
    stop: threading.Event | None = None,
) -> State | None:
    """Watch the Job of a `running` attempt whose watcher was lost (a worker killed): the
    reconciler asks for this when the Job still exists, so the evaluation is not thrown away."""
    from server.challenges.service import suite_of

    with sessions() as db:
        submission = db.get(Submission, submission_id)
        if submission is None or submission.attempt != attempt:
            return None
        if submission.state != State.RUNNING:
            return submission.state
        suite = suite_of(submission.challenge)
        suite_yaml, phase = submission.challenge.suite_yaml, submission.phase.name
        pinned = submission.pinned_image
    try:
        watch = _watch_for(
            sessions, settings, submission_id, attempt, suite, suite_yaml, phase, pinned, stop
        )
    except Exception as exc:
        return finish(sessions, submission_id, attempt, State.ERROR, f"cannot run: {exc}")
    log.info("resuming the watch of Job %s", watch.spec.name)
    return _guarded(watch, watch.follow)


def _watch_for(
    sessions: sessionmaker[Session],
    settings: Settings,
    submission_id: int,
    attempt: int,
    suite: Suite,
    suite_yaml: str,
    phase: str,
    pinned: str,
    stop: threading.Event | None,
) -> _Watch:
    plan = build_plan(suite, phase, secret=settings.secret("seed_secret").encode())
    spec = job_spec(
        settings, submission_id, attempt, plan, suite=suite, suite_yaml=suite_yaml, pinned=pinned
    )
    executor = kubernetes_executor(settings)
    return _Watch(sessions, settings, executor, spec, plan, stop or threading.Event())


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
    sessions: sessionmaker[Session]
    settings: Settings
    executor: KubernetesExecutor
    spec: JobSpec
    plan: EvaluationPlan
    stop: threading.Event
    _looks: int = 0
    _read_progress: dict[str, Any] = field(default_factory=dict)

    @property
    def ids(self) -> tuple[int, int]:
        return self.spec.submission_id, self.spec.attempt

    def run(self) -> State | None:
        deadline = utcnow() + timedelta(
            seconds=self.spec.active_deadline_seconds + DEADLINE_GRACE_S
        )
        reason = f"evaluating as Kubernetes Job {self.spec.name}"
        if not start_running(self.sessions, *self.ids, deadline, reason):
            return final_state(self.sessions, self.spec.submission_id)
        try:
            started = self.executor.start(self.spec)
        except JobConflict as exc:  # not ours to delete: another deployment's, or being deleted
            reason = f"cannot create the evaluation Job: {exc}"
            return finish(self.sessions, *self.ids, State.ERROR, reason)
        except KubernetesError as exc:
            return self.end(State.ERROR, f"cannot create the evaluation Job: {exc}")
        if started.adopted:
            log.info("adopted the existing Job %s", started.name)
        return self.follow()

    def follow(self) -> State | None:
        """Look at the Job until it ends (or the attempt ends elsewhere)."""
        outage_since: float | None = None
        while not self.stop.wait(self.settings.k8s_poll_interval):
            try:
                status = self.executor.status(*self.ids)
                if status.phase in ("pending", "running"):
                    ended = self._look(status)
                    outage_since = None
                    if ended is not None:
                        return ended
                    continue
            except KubernetesError as exc:
                now = time.monotonic()
                outage_since = outage_since if outage_since is not None else now
                log.warning("Job %s: the API server failed: %s", self.spec.name, exc)
                if now - outage_since > API_OUTAGE_S:
                    return self.end(State.ERROR, f"the Kubernetes API failed for too long: {exc}")
                if not self._beat({"phase": "unknown"}):
                    return self._cancelled()
                continue
            return self._concluded(status)
        return final_state(self.sessions, self.spec.submission_id)

    def _look(self, status: JobStatus) -> State | None:
        """One look at a live Job: stuck pods end it, else report progress (the heartbeat)."""
        view = self.executor.pods(*self.ids)
        if view.stuck is not None:
            return self.end(State.ERROR, f"the evaluation could not start: {view.stuck}")
        progress: dict[str, Any] = {"phase": status.phase, "done": 0}
        if view.evaluating:
            if self._looks % PROGRESS_EVERY == 0:  # the log is the costly read: not every look
                self._read_progress = self._progress()
            self._looks += 1
            progress |= self._read_progress
        if not self._beat(progress):
            return self._cancelled()
        return None

    def _progress(self) -> dict[str, Any]:
        logs = self.executor.collect(*self.ids, container=EVALUATOR)
        done, last = episodes_in(logs)
        progress: dict[str, Any] = {"done": done, "total": self.plan.episode_count()}
        if last is not None and last < len(self.plan.runs):
            run = self.plan.runs[last]
            progress |= {"task": run.env_id, "condition": run.condition.name}
        return progress

    def _beat(self, progress: dict[str, Any]) -> bool:
        progress.setdefault("total", self.plan.episode_count())
        with self.sessions.begin() as db:
            return report_progress(db, *self.ids, progress)

    def _concluded(self, status: JobStatus) -> State | None:
        if status.phase == "succeeded":
            return self._collect()
        if status.phase == "deadline_exceeded":
            if self.executor.pods(*self.ids).disrupted:  # the cluster's doing, not the policy's
                reason = "the cluster evicted the evaluation and it then ran out of time"
                return self.end(State.ERROR, reason)
            return self.end(State.TIMED_OUT, "the evaluation exceeded its time budget")
        if status.phase == "missing":
            return self.end(State.ERROR, f"the evaluation's Job {self.spec.name} disappeared")
        return self.end(State.ERROR, f"the evaluator failed ({status.reason})")

    def _collect(self) -> State | None:
        try:
            logs = self.executor.collect(*self.ids, container=EVALUATOR)
            result = result_from_logs(self.plan, logs)
        except (KubernetesError, JobOutputError) as exc:
            return self.end(State.ERROR, f"the evaluation's result could not be read: {exc}")
        policy_ended, policy_log = self._policy_side()
        state = conclude(self.sessions, *self.ids, result, log_tail=policy_log, detail=policy_ended)
        self._delete()
        return state

    def _policy_side(self) -> tuple[str | None, str]:
        """How the policy container ended and its log tail: extras that never cost a result."""
        try:
            view = self.executor.pods(*self.ids)
            logs = self.executor.collect(*self.ids, container=POLICY, tail_lines=POLICY_LOG_LINES)
        except KubernetesError as exc:
            log.warning("Job %s: the policy's side could not be read: %s", self.spec.name, exc)
            return None, ""
        text = "\n".join(log.rstrip("\n") for log in logs if log)
        return view.policy_ended, text[-LOG_TAIL_BYTES:]

    def end(self, state: State, reason: str) -> State | None:
        log.info("Job %s: %s: %s", self.spec.name, state.value, reason)
        ended = finish(self.sessions, *self.ids, state, reason)
        self._delete()
        return ended

    def _cancelled(self) -> State | None:
        """The attempt ended elsewhere (cancel, the reconciler): its Job goes too."""
        self._delete()
        return final_state(self.sessions, self.spec.submission_id)

    def _delete(self) -> None:
        try:
            self.executor.cancel(*self.ids)
        except KubernetesError as exc:  # the reconciler deletes it on its next pass
            log.warning("could not delete Job %s: %s", job_name(*self.ids), exc)


def episodes_in(logs: Sequence[str]) -> tuple[int, int | None]:
    """Episodes the evaluator logs report done, and the run index of the last one."""
    done, last = 0, None
    for text in logs:
        for match in _EPISODE_LINE.finditer(text):
            done += 1
            last = int(match.group(1))
    return done, last
