"""Run one attempt of one submission to a final state, reporting as it goes.

The same code runs in the embedded server's worker thread and in a Celery task: it takes ids,
reloads state, returns early when there is nothing left to do, and every path out of it,
including an exception of ours, ends the attempt with a reason. Bundled `local:` policies and
the `docker` executor evaluate here, in the worker; with `kubernetes` the attempt becomes a Job
(`worker.kubernetes.watch`) and this process watches it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.sources import LocalDirectory, PolicySource
from server.challenges.service import suite_of
from server.kit.settings import Settings
from server.models import State, Submission, utcnow
from server.submissions.reports import report_progress
from server.submissions.service import LOCAL_PREFIX
from worker.outcome import conclude, final_state, finish, start_running
from worker.reconcile import Cleaner, Resumer
from worker.scheduling import claim_next

log = logging.getLogger(__name__)

EXAMPLES_DIR = Path(__file__).resolve().parent.parent / "examples" / "policies"
PROGRESS_INTERVAL_S = 1.0
HEARTBEAT_INTERVAL_S = 15.0
DEADLINE_GRACE_S = 120.0  # beyond the suite's budget, before the reconciler times a run out


class NotRunnable(Exception):
    """The submission cannot be run by this worker's configuration (our error, not theirs)."""


def local_policies() -> dict[str, Path]:
    """The bundled example policies a demo may submit as ``local:NAME``."""
    return {p.name: p for p in sorted(EXAMPLES_DIR.iterdir()) if (p / "policy.py").is_file()}


def policy_source(
    pinned: str, settings: Settings, *, submission_id: int, attempt: int
) -> PolicySource:
    """Where the attempt's policy comes from: a bundled directory (demo) or a pinned image."""
    if pinned.startswith(LOCAL_PREFIX):
        if not settings.allow_local_policies:
            raise NotRunnable("local policies are disabled on this server")
        name = pinned.removeprefix(LOCAL_PREFIX)
        directory = local_policies().get(name)
        if directory is None:
            raise NotRunnable(f"no bundled policy {name!r}")
        return LocalDirectory(directory)
    if settings.docker_engine_url is None:
        raise NotRunnable("no container engine is configured (MANIEVAL_DOCKER_ENGINE_URL)")
    from worker.containers import ContainerImage, ContainerLimits

    limits = ContainerLimits(memory_mib=settings.policy_memory_mib, cpus=settings.policy_cpus)
    return ContainerImage(
        pinned,
        submission=submission_id,
        attempt=attempt,
        engine_url=settings.docker_engine_url,
        limits=limits,
    )


def runtime_cleaners(settings: Settings) -> list[Cleaner]:
    """The reconciler's view of what runs evaluations: remove the containers and Jobs of
    attempts that are no longer active (a worker crashed, or lost its connection)."""
    cleaners: list[Cleaner] = []
    url = settings.docker_engine_url
    if url is not None:

        def clean_containers(active: set[tuple[int, int]]) -> list[str]:
            from worker.containers import attempt_key, engine, remove_leftovers

            keep = {attempt_key(sid, attempt) for sid, attempt in active}
            return remove_leftovers(engine(url), keep=keep)

        cleaners.append(clean_containers)
    if settings.executor == "kubernetes":

        def clean_jobs(active: set[tuple[int, int]]) -> list[str]:
            from worker.kubernetes.watch import kubernetes_executor

            executor = kubernetes_executor(settings)
            try:
                return executor.delete_orphans(keep=active)
            finally:
                executor.close()

        cleaners.append(clean_jobs)
    return cleaners


def job_resumer(settings: Settings, send: Callable[[int, int], None]) -> Resumer | None:
    """With Kubernetes, a silent attempt's Job may still be running (or done): `send` a new
    watcher for it rather than throwing the evaluation away. None for other executors."""
    if settings.executor != "kubernetes":
        return None

    def resume(submission_id: int, attempt: int) -> bool:
        from worker.kubernetes.watch import kubernetes_executor

        executor = kubernetes_executor(settings)
        try:
            if executor.status(submission_id, attempt).phase == "missing":
                return False
        finally:
            executor.close()
        send(submission_id, attempt)
        return True

    return resume


def run_next(
    sessions: sessionmaker[Session], settings: Settings
) -> tuple[int, State | None] | None:
    """Claim the fairest queued submission and run it to a final state.

    Returns (submission id, final state), or None when nothing could be claimed. Any number of
    workers may call this at once: a claim is a conditional update only one of them wins.
    """
    with sessions() as db:
        claimed = claim_next(db, max_running_per_user=settings.max_running_per_user)
    if claimed is None:
        return None
    submission_id, attempt = claimed
    return submission_id, execute(sessions, settings, submission_id, attempt)


def execute(
    sessions: sessionmaker[Session], settings: Settings, submission_id: int, attempt: int
) -> State | None:
    """Run a claimed (`launching`) attempt; returns the state it ended in."""
    with sessions() as db:
        submission = db.get(Submission, submission_id)
        if submission is None or submission.attempt != attempt:
            return None
        if submission.state != State.LAUNCHING:
            return submission.state  # cancelled between the claim and now
        suite = suite_of(submission.challenge)
        suite_yaml = submission.challenge.suite_yaml
        phase = submission.phase.name
        pinned = submission.pinned_image
    if settings.executor == "kubernetes" and not pinned.startswith(LOCAL_PREFIX):
        from worker.kubernetes.watch import run_as_job

        return run_as_job(
            sessions,
            settings,
            submission_id,
            attempt,
            suite=suite,
            suite_yaml=suite_yaml,
            phase=phase,
            pinned=pinned,
        )
    try:
        source = policy_source(pinned, settings, submission_id=submission_id, attempt=attempt)
        pull = getattr(source, "pull", None)
        if pull is not None:
            pull()  # before `running`: pulling time is not the policy's budget
        # The same key `MANIEVAL_SEED_SECRET=... manieval evaluate --phase test` uses offline.
        secret = settings.secret("seed_secret").encode()
        plan = build_plan(suite, phase, secret=secret)
    except Exception as exc:  # our configuration: error, with the reason
        return finish(sessions, submission_id, attempt, State.ERROR, f"cannot run: {exc}")

    deadline = utcnow() + timedelta(seconds=plan.limits.budget_s * 1.1 + DEADLINE_GRACE_S)
    if not start_running(sessions, submission_id, attempt, deadline):
        return final_state(sessions, submission_id)
    try:
        result = _evaluate(sessions, submission_id, attempt, plan, source)
    except Exception as exc:
        log.exception("evaluation of submission %s attempt %s crashed", submission_id, attempt)
        return finish(
            sessions,
            submission_id,
            attempt,
            State.ERROR,
            f"the evaluator failed: {type(exc).__name__}: {exc}",
        )
    if result is None:  # cancelled while running: the cancel already recorded the state
        return final_state(sessions, submission_id)
    return conclude(sessions, submission_id, attempt, result)


def _evaluate(
    sessions: sessionmaker[Session],
    submission_id: int,
    attempt: int,
    plan: EvaluationPlan,
    source: PolicySource,
) -> EvaluationResult | None:
    from evaluator.evaluation import evaluate

    total = plan.episode_count()
    done = 0
    last_report = 0.0
    progress: dict[str, Any] = {"done": 0, "total": total}
    stopped = threading.Event()
    finished = threading.Event()
    lock = threading.Lock()

    def send() -> None:
        with lock:
            snapshot = dict(progress)
        with sessions.begin() as db:
            if not report_progress(db, submission_id, attempt, snapshot):
                stopped.set()  # cancelled, or timed out or given up by the reconciler

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
        send()

    def heartbeat() -> None:  # also while an episode or a slow first call takes long
        while not finished.wait(HEARTBEAT_INTERVAL_S):
            try:
                send()
            except Exception:
                log.exception("heartbeat of submission %s failed", submission_id)

    beat = threading.Thread(target=heartbeat, name=f"heartbeat-{submission_id}", daemon=True)
    beat.start()
    try:
        result = evaluate(plan, source, on_episode=report, should_stop=stopped.is_set)
    finally:
        finished.set()
        beat.join()
    return None if stopped.is_set() else result
