"""Celery on Redis: the same task code as the embedded worker, spread over worker processes.

    celery -A worker.celery_app worker --concurrency 1    # one evaluation per process
    celery -A worker.celery_app beat                      # the reconciler, every 30 s

With MANIEVAL_EXECUTOR=kubernetes a task only watches its Job, so one worker process can run
many (`--pool threads --concurrency 16`): the evaluations run in the cluster.

Messages carry no work, only a wake-up: the task claims the fairest queued submission from
the database. So `acks_late` is safe (a redelivered message claims nothing twice), a worker's
prefetch of one cannot hoard long evaluations, and a lost message is replaced by the
reconciler's next wake-up.
"""

from __future__ import annotations

import functools
import logging
from typing import Any

from celery import Celery
from celery.signals import setup_logging
from sqlalchemy.orm import Session, sessionmaker

from server.kit.db import make_engine, session_factory
from server.kit.settings import Settings
from worker.queue import RUN_NEXT, WATCH, CeleryQueue

log = logging.getLogger(__name__)
RECONCILE = "manieval.reconcile"


def make_app(settings: Settings) -> Celery:
    celery = Celery("manieval", broker=settings.broker_url)
    celery.conf.update(
        task_default_queue=settings.celery_queue,
        task_serializer="json",
        accept_content=["json"],  # never pickle: messages cross a trust boundary (the broker)
        task_ignore_result=True,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        broker_connection_retry_on_startup=True,
        beat_schedule={"reconcile": {"task": RECONCILE, "schedule": 30.0}},
    )
    celery.task(name=RUN_NEXT, acks_late=True)(_run_next)
    celery.task(name=RECONCILE, acks_late=False)(_reconcile)
    celery.task(name=WATCH, acks_late=True)(_watch)
    return celery


@functools.cache
def _settings() -> Settings:
    return Settings()


@functools.cache
def _sessions() -> sessionmaker[Session]:
    return session_factory(make_engine(_settings().resolved_database_url))


def _run_next(submission_id: int = 0, attempt: int = 0) -> Any:
    """Run the fairest queued submission (the ids only say which submission woke us)."""
    from worker.run import run_next

    outcome = run_next(_sessions(), _settings())
    if outcome is None:
        return None
    sid, state = outcome
    log.info("submission %s (woken by %s/%s) ended %s", sid, submission_id, attempt, state)
    CeleryQueue(_settings()).enqueue(0, 0)  # there may be more waiting: keep the queue moving
    return {"submission": sid, "state": state.value if state else None}


def _reconcile() -> Any:
    from worker.reconcile import reconcile
    from worker.run import job_resumer, runtime_cleaners

    queue = CeleryQueue(_settings())
    report = reconcile(
        _sessions(),
        queue,
        cleaners=runtime_cleaners(_settings()),
        resume=job_resumer(_settings(), queue.watch),
    )
    return {
        "timed_out": report.timed_out,
        "lost": report.lost,
        "resumed": report.resumed,
        "woken": report.woken,
    }


def _watch(submission_id: int, attempt: int) -> Any:
    """Take over watching a running attempt's Job (its first watcher was lost)."""
    from worker.kubernetes.watch import resume_watch

    state = resume_watch(_sessions(), _settings(), submission_id, attempt)
    return {"submission": submission_id, "state": state.value if state else None}


def _logging(**_kwargs: Any) -> None:
    """Celery's records go through ours: text or JSON lines (MANIEVAL_LOG_FORMAT)."""
    from server.kit.observability import configure_logging

    configure_logging(_settings().log_format, _settings().log_level)


setup_logging.connect(_logging)
app = make_app(_settings())
