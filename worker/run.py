"""Run one attempt of one submission to a final state, reporting as it goes.

The same code runs in the embedded server's worker threads and in a Celery task: it claims
through the internal API, is handed the evaluation with its concrete seeds, and every path out
of it, including an exception of ours, ends the attempt with a reason. Bundled `local:`
policies and the `docker` executor evaluate here, in the worker; with `kubernetes` the attempt
becomes a Job (`worker.kubernetes.watch`) and this process watches it.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluator.bundled import LOCAL_PREFIX, bundled_policies
from evaluator.plan import EvaluationPlan
from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.sources import LocalDirectory, PolicySource
from internal_api.schemas import Assignment, State
from worker.deadline import wall_clock_limit_s
from worker.outcome import conclusion, ended
from worker.server_api import ServerAPI, ServerUnavailable
from worker.settings import WorkerSettings
from worker.videos import recording_dir, upload_trajectories, upload_videos

log = logging.getLogger(__name__)

PROGRESS_INTERVAL_S = 1.0
HEARTBEAT_INTERVAL_S = 1.0  # also how soon a cancel is seen mid-episode


class NotRunnable(Exception):
    """The submission cannot be run by this worker's configuration (our error, not theirs)."""


@dataclass(frozen=True)
class Ended:
    """An attempt the server ended while it ran (a cancel, the reconciler's timeout), with the
    result of what ran until the worker saw it: the server keeps it beside its own end."""

    state: State
    result: EvaluationResult | None = None


def policy_source(
    image: str, settings: WorkerSettings, *, submission_id: int, attempt: int, gpus: int = 0
) -> PolicySource:
    """Where the attempt's policy comes from: a bundled directory (demo) or a pinned image
    (given `gpus` GPUs)."""
    if image.startswith(LOCAL_PREFIX):
        if not settings.allow_local_policies:
            raise NotRunnable("local policies are disabled on this worker")
        name = image.removeprefix(LOCAL_PREFIX)
        directory = bundled_policies().get(name)
        if directory is None:
            raise NotRunnable(f"no bundled policy {name!r}")
        return LocalDirectory(directory)
    if settings.docker_engine_url is None:
        raise NotRunnable("no container engine is configured (MANIEVAL_DOCKER_ENGINE_URL)")
    from worker.containers import ContainerImage, ContainerLimits

    limits = ContainerLimits(memory_mib=settings.policy_memory_mib, cpus=settings.policy_cpus)
    return ContainerImage(
        image,
        submission=submission_id,
        attempt=attempt,
        engine_url=settings.docker_engine_url,
        limits=limits,
        service=settings.service_id,
        gpus=gpus,
    )


def run_next(api: ServerAPI, settings: WorkerSettings) -> tuple[int, State | None] | None:
    """Claim the fairest queued submission and run it to a final state.

    Returns (submission id, final state), or None when nothing could be claimed. Any number of
    workers may call this at once: a claim is a conditional update only one of them wins.
    """
    handed = api.claim(settings.worker_name)
    if handed is None:
        return None
    return handed.submission_id, execute(api, settings, handed)


def execute(api: ServerAPI, settings: WorkerSettings, handed: Assignment) -> State | None:
    """Run a claimed (`launching`) attempt; returns the state it ended in (None: unknown,
    its final report waits in the spool, or the worker was stopped under it).

    A stop of the worker (`api.stop`) interrupts the evaluation within about a second, its
    policy process or container gone, and reports nothing: what was cut short is no result
    of the policy's, and the attempt stays in flight for whoever stopped the worker to record
    (the embedded service queues it again, `server.submissions.work.end_stopped`).
    """
    sid, attempt = handed.submission_id, handed.attempt
    refusal = handed.plan.policy.refusal(available=settings.policy_gpus)
    if refusal is not None:  # the server's MANIEVAL_POLICY_GPUS promised more than we have
        return api.final(sid, attempt, ended(State.ERROR, f"cannot run: {refusal}"))
    if settings.executor == "kubernetes" and not handed.image.startswith(LOCAL_PREFIX):
        from worker.kubernetes.watch import run_as_job

        # A stop ends the watch at once: the embedded service records the attempt interrupted,
        # and the reconciler removes its Job (no longer an active attempt's).
        return run_as_job(api, settings, handed, stop=api.stop)
    try:
        source = policy_source(
            handed.image,
            settings,
            submission_id=sid,
            attempt=attempt,
            gpus=handed.plan.policy.gpus,
        )
        pull = getattr(source, "pull", None)
        if pull is not None:
            pull()  # before `running`: pulling time is not the policy's budget
    except Exception as exc:  # our configuration: error, with the reason
        if api.stop.is_set():
            _interrupted(sid, attempt)
            return None
        return api.final(sid, attempt, ended(State.ERROR, f"cannot run: {exc}"))
    if api.stop.is_set():
        _interrupted(sid, attempt)
        return None

    plan = handed.plan
    deadline_s = wall_clock_limit_s(plan)
    started = api.running(sid, attempt, reason="evaluating", deadline_s=deadline_s)
    if started is None or not started.applied:
        return started.state if started is not None else None
    try:
        result = _evaluate_recording(api, settings, sid, attempt, plan, source)
    except Exception as exc:
        if api.stop.is_set():  # whatever broke while stopping is no fault to report
            log.warning("submission %s stopped with %s: %s", sid, type(exc).__name__, exc)
            _interrupted(sid, attempt)
            return None
        log.exception("evaluation of submission %s attempt %s crashed", sid, attempt)
        reason = f"the evaluator failed: {type(exc).__name__}: {exc}"
        return api.final(sid, attempt, ended(State.ERROR, reason))
    if result is None:
        _interrupted(sid, attempt)
        return None
    if isinstance(result, Ended):  # cancelled or timed out meanwhile: recorded, but not what ran
        if result.result is not None:
            api.final(sid, attempt, ended(result.state, "what ran", result=result.result))
        return result.state
    return api.final(sid, attempt, conclusion(result))


def _interrupted(sid: int, attempt: int) -> None:
    log.info("submission %s attempt %s interrupted: the worker is stopping", sid, attempt)


def _evaluate_recording(
    api: ServerAPI,
    settings: WorkerSettings,
    sid: int,
    attempt: int,
    plan: EvaluationPlan,
    source: PolicySource,
) -> EvaluationResult | Ended | None:
    """`_evaluate`, with the plan's episode videos and every episode's trajectory recorded
    and stored on the server before the final report (the page shows them as soon as the
    result is there)."""
    processes = settings.evaluation_processes
    with recording_dir(settings, submission_id=sid, attempt=attempt) as directory:
        trajectories = directory / "trajectories"
        result = _evaluate(
            api,
            sid,
            attempt,
            plan,
            source,
            processes=processes,
            video_dir=directory if plan.videos else None,
            trajectory_dir=trajectories,
        )
        if not isinstance(result, EvaluationResult):
            return result  # the recordings of an attempt that ended are not kept
        result = upload_videos(
            api, submission_id=sid, attempt=attempt, result=result, directory=directory
        )
        upload_trajectories(
            api, submission_id=sid, attempt=attempt, result=result, directory=trajectories
        )
        return result


def _evaluate(
    api: ServerAPI,
    sid: int,
    attempt: int,
    plan: EvaluationPlan,
    source: PolicySource,
    *,
    processes: int,
    video_dir: Path | None = None,
    trajectory_dir: Path | None = None,
) -> EvaluationResult | Ended | None:
    """The result, or the state the attempt was ended in elsewhere while it ran, or None when
    the worker's stop interrupted it. With `processes`, the simulator runs in that many warm
    evaluator processes (`evaluator.pool`), not in this one, whose other threads (the embedded
    worker's, the server's) would share its Python lock; with 0, here."""
    from evaluator.evaluation import evaluate

    total = plan.episode_count()
    done = 0
    last_report = 0.0
    progress: dict[str, Any] = {"done": 0, "total": total}
    stopped = threading.Event()
    stopped_as: list[State] = []
    interrupted = threading.Event()
    finished = threading.Event()
    wake = threading.Event()  # an episode's report asks the heartbeat to send now
    sent: list[dict[str, Any]] = []  # the last progress sent
    lock = threading.Lock()

    def should_stop() -> bool:
        if api.stop.is_set():
            interrupted.set()
            return True
        return stopped.is_set()

    def send(*, unless_sent: bool = False) -> None:
        if api.stop.is_set():  # stopping: nothing of this run is reported any more
            return
        with lock:
            snapshot = dict(progress)
        if unless_sent and sent and snapshot == sent[-1]:
            return
        sent[-1:] = [snapshot]
        try:
            out = api.progress(sid, attempt, snapshot)
            if not out.applied:  # cancelled, or timed out or given up by the reconciler
                stopped_as.append(out.state)
                stopped.set()
        except ServerUnavailable as exc:  # the next beat tries again; the run goes on
            log.warning("progress of submission %s not delivered: %s", sid, exc)

    def report(run_index: int, _episode: EpisodeResult) -> None:
        nonlocal done, last_report
        with lock:
            done += 1
            run = plan.runs[run_index]
            progress.update(done=done, task=run.env_id, condition=run.condition.name)
            now = time.monotonic()
            if now - last_report < PROGRESS_INTERVAL_S and done < total:
                return
            last_report = now
        wake.set()

    def heartbeat() -> None:
        """Send the progress every HEARTBEAT_INTERVAL_S (also while an episode or a slow first
        call takes long) and when an episode's report asks: from this thread, never the
        evaluation's, so a server that does not answer (a worker cut off from it) costs the
        episodes nothing. Once the run finished, what the last report said, if not sent yet."""
        while True:
            wake.wait(HEARTBEAT_INTERVAL_S)
            wake.clear()
            last = finished.is_set()
            try:
                send(unless_sent=last)
            except Exception:
                log.exception("heartbeat of submission %s failed", sid)
            if last:
                return

    beat = threading.Thread(target=heartbeat, name=f"heartbeat-{sid}", daemon=True)
    beat.start()
    try:
        result = evaluate(
            plan,
            source,
            workers=max(processes, 1),
            warm=processes > 0,
            video_dir=video_dir,
            trajectory_dir=trajectory_dir,
            on_episode=report,
            should_stop=should_stop,
        )
    finally:
        finished.set()
        wake.set()
        beat.join()
    if stopped_as:
        return Ended(stopped_as[0], None if interrupted.is_set() else result)
    return None if interrupted.is_set() else result
