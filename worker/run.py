"""Run one attempt of one submission to a final state, reporting as it goes.

The same code runs in the embedded server's worker thread and (with the worker issue) in a
Celery task: it takes ids, reloads state, returns early when there is nothing left to do, and
every path out of it, including an exception of ours, ends the attempt with a reason.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.sources import LocalDirectory, PolicySource
from server.challenges import seed_secret_for, suite_of
from server.errors import Conflict
from server.ingest import report_final, report_progress, report_state
from server.models import State, Submission
from server.settings import Settings
from server.submissions import LOCAL_PREFIX

log = logging.getLogger(__name__)

EXAMPLES_DIR = Path(__file__).resolve().parent.parent / "examples" / "policies"
PROGRESS_INTERVAL_S = 1.0


class NotRunnable(Exception):
    """The submission cannot be run by this worker's configuration (our error, not theirs)."""


def local_policies() -> dict[str, Path]:
    """The bundled example policies a demo may submit as ``local:NAME``."""
    return {p.name: p for p in sorted(EXAMPLES_DIR.iterdir()) if (p / "policy.py").is_file()}


def policy_source(pinned: str, settings: Settings) -> PolicySource:
    if pinned.startswith(LOCAL_PREFIX):
        if not settings.allow_local_policies:
            raise NotRunnable("local policies are disabled on this server")
        name = pinned.removeprefix(LOCAL_PREFIX)
        directory = local_policies().get(name)
        if directory is None:
            raise NotRunnable(f"no bundled policy {name!r}")
        return LocalDirectory(directory)
    raise NotRunnable("no container executor is configured on this worker")


def run_submission(
    sessions: sessionmaker[Session], settings: Settings, submission_id: int, attempt: int
) -> State | None:
    """Run the attempt if it is still queued; returns the final state it reached (None if the
    attempt was not this worker's to run)."""
    with sessions.begin() as db:
        submission = db.get(Submission, submission_id)
        if submission is None or submission.attempt != attempt:
            return None
        if submission.state != State.QUEUED:
            return None  # already taken, cancelled, or done: nothing to do
        if not report_state(db, submission_id, attempt, State.LAUNCHING, "starting the policy"):
            return None
        suite = suite_of(submission.challenge)
        phase = submission.phase.name
        pinned = submission.pinned_image
    try:
        source = policy_source(pinned, settings)
        secret = seed_secret_for(settings.secret("seed_secret"), suite.name)
        plan = build_plan(suite, phase, secret=secret)
    except Exception as exc:  # our configuration: error, with the reason
        return _finish(sessions, submission_id, attempt, State.ERROR, f"cannot run: {exc}")

    with sessions.begin() as db:
        if not report_state(db, submission_id, attempt, State.RUNNING, "evaluating"):
            return _final_state(sessions, submission_id)
    try:
        result = _evaluate(sessions, submission_id, attempt, plan, source)
    except Exception as exc:
        log.exception("evaluation of submission %s attempt %s crashed", submission_id, attempt)
        return _finish(
            sessions,
            submission_id,
            attempt,
            State.ERROR,
            f"the evaluator failed: {type(exc).__name__}: {exc}",
        )
    if result is None:  # cancelled while running: the cancel already recorded the state
        return _final_state(sessions, submission_id)
    if result.status == "aborted" and result.abort is not None:
        abort = result.abort
        state = State.TIMED_OUT if abort.kind == "budget_exhausted" else State.FAILED
        return _finish(
            sessions,
            submission_id,
            attempt,
            state,
            abort.reason,
            result=result,
            log_tail=abort.log_tail,
        )
    return _finish(
        sessions,
        submission_id,
        attempt,
        State.SUCCEEDED,
        f"score {result.score:.3f}",
        result=result,
    )


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
    stopped = threading.Event()
    lock = threading.Lock()

    def report(run_index: int, _episode: EpisodeResult) -> None:
        nonlocal done, last_report
        with lock:
            done += 1
            now = time.monotonic()
            if now - last_report < PROGRESS_INTERVAL_S and done < total:
                return
            last_report = now
            run = plan.runs[run_index]
            progress = {
                "done": done,
                "total": total,
                "task": run.env_id,
                "condition": run.condition.name,
            }
        with sessions.begin() as db:
            if not report_progress(db, submission_id, attempt, progress):
                stopped.set()  # cancelled or timed out by the reconciler

    def should_stop() -> bool:
        return stopped.is_set()

    result = evaluate(plan, source, on_episode=report, should_stop=should_stop)
    return None if stopped.is_set() else result


def _finish(
    sessions: sessionmaker[Session],
    submission_id: int,
    attempt: int,
    state: State,
    reason: str,
    *,
    result: EvaluationResult | None = None,
    log_tail: str = "",
) -> State | None:
    try:
        with sessions.begin() as db:
            report_final(
                db, submission_id, attempt, state, reason, result=result, log_tail=log_tail
            )
    except Conflict:
        pass  # a re-run replaced this attempt
    return _final_state(sessions, submission_id)


def _final_state(sessions: sessionmaker[Session], submission_id: int) -> State | None:
    with sessions() as db:
        submission = db.get(Submission, submission_id)
        return submission.state if submission is not None else None


OnDone = Callable[[int, int, State | None], None]
