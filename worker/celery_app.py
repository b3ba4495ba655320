"""Celery on Redis: the same task code as the embedded worker, spread over worker processes.

    celery -A worker.celery_app worker --concurrency 1    # one evaluation per process
    celery -A worker.celery_app worker -Q manieval-reconcile --beat   # the reconciler, every 30 s

A worker process needs the broker URL, the server's URL and the worker token, nothing more:
it claims work and reports through the server's internal API. With
MANIEVAL_EXECUTOR=kubernetes a task only watches its Job, so one worker process can run many
(`--pool threads --concurrency 16`): the evaluations run in the cluster.

Messages carry no work, only a wake-up: the task claims the fairest queued submission from
the server. So `acks_late` is safe (a redelivered message claims nothing twice), a worker's
prefetch of one cannot hoard long evaluations, and a lost message is replaced by the
reconciler's next wake-up. The reconciler has its own queue, so busy workers never delay it.
"""

from __future__ import annotations

import functools
import logging
from typing import Any

from celery import Celery
from celery.signals import setup_logging, worker_init, worker_ready, worker_shutdown

from internal_api.tasks import RECONCILE, RUN_NEXT, WATCH
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings
from worker.spool_sender import SpoolSender

log = logging.getLogger(__name__)
RECONCILE_EVERY_S = 30.0


def make_app(settings: WorkerSettings) -> Celery:
    celery = Celery("manieval", broker=settings.broker_url)
    celery.conf.update(
        task_default_queue=settings.celery_queue,
        task_routes={RECONCILE: {"queue": settings.reconcile_queue}},
        task_serializer="json",
        accept_content=["json"],  # never pickle: messages cross a trust boundary (the broker)
        task_ignore_result=True,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        broker_connection_retry_on_startup=True,
        beat_schedule={
            "reconcile": {
                "task": RECONCILE,
                "schedule": RECONCILE_EVERY_S,
                "options": {"queue": settings.reconcile_queue, "expires": RECONCILE_EVERY_S},
            }
        },
    )
    celery.task(name=RUN_NEXT, acks_late=True)(_run_next)
    celery.task(name=RECONCILE, acks_late=False)(_reconcile)
    celery.task(name=WATCH, acks_late=True)(_watch)
    return celery


@functools.cache
def _settings() -> WorkerSettings:
    return WorkerSettings()  # type: ignore[call-arg]  # the token comes from the environment


@functools.cache
def _api() -> ServerAPI:
    return ServerAPI.connect(_settings())


def _run_next(submission_id: int = 0, attempt: int = 0) -> Any:
    """Run the fairest queued submission (the ids only say which submission woke us)."""
    from worker.run import run_next

    outcome = run_next(_api(), _settings())
    if outcome is None:
        return None
    sid, state = outcome
    log.info("submission %s (woken by %s/%s) ended %s", sid, submission_id, attempt, state)
    app.send_task(RUN_NEXT, args=[0, 0])  # there may be more waiting: keep the queue moving
    return {"submission": sid, "state": state.value if state else None}


def _reconcile() -> Any:
    from worker.reconcile import job_resumer, reconcile_pass, runtime_cleaners

    report = reconcile_pass(
        _api(),
        cleaners=runtime_cleaners(_settings()),
        resume=job_resumer(_settings(), _send_watch),
    )
    return {
        "timed_out": report.server.timed_out,
        "lost": report.server.lost,
        "resumed": report.resumed,
        "woken": report.server.woken,
    }


def _send_watch(submission_id: int, attempt: int) -> None:
    app.send_task(WATCH, args=[submission_id, attempt])


def _watch(submission_id: int, attempt: int) -> Any:
    """Take over watching a running attempt's Job (its first watcher was lost)."""
    from worker.kubernetes.watch import resume_watch

    state = resume_watch(_api(), _settings(), submission_id, attempt)
    return {"submission": submission_id, "state": state.value if state else None}


def _started(**_kwargs: Any) -> None:
    """Before the first task: send the final reports an earlier run kept, then end (and
    re-queue) the attempts that died with this worker's previous run, if its name is stable.
    Done before consuming, so it cannot end an attempt this run has just claimed; its own
    client, since the pool's processes fork after this."""
    api = ServerAPI.connect(_settings())
    try:
        sent = api.flush_spool()
        ended = api.restarted(_settings().worker_name)
    except Exception:
        log.exception("settling what an earlier run left failed; the reconciler will")
        return
    finally:
        api.close()
    if sent or ended:
        log.info("sent %s kept final reports; ended %s attempts of an earlier run", sent, ended)


@functools.cache
def _sender() -> SpoolSender:
    return SpoolSender(ServerAPI.connect(_settings()), every_s=_settings().spool_retry_s)


def _ready(**_kwargs: Any) -> None:
    """Once the pool runs: try the spool again every `spool_retry_s` while the worker runs,
    from a thread of this process (the pool's processes, forked before it, share the spool)."""
    _sender().start()


def _stopping(**_kwargs: Any) -> None:
    _sender().stop(timeout=_settings().request_timeout_s)


def _logging(**_kwargs: Any) -> None:
    """Celery's records go through ours: text or JSON lines (MANIEVAL_LOG_FORMAT)."""
    from internal_api.logs import configure_logging

    configure_logging(_settings().log_format, _settings().log_level)


setup_logging.connect(_logging)
worker_init.connect(_started)
worker_ready.connect(_ready)
worker_shutdown.connect(_stopping)
app = make_app(_settings())
