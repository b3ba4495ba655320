"""The server's side of the Celery queue: wake-ups sent to the workers through Redis."""

from __future__ import annotations

import functools

from celery import Celery

from server.kit.settings import Settings

RUN_NEXT = "manieval.run_next"
WATCH = "manieval.watch"


class CeleryQueue:
    """The server's side: hand a wake-up to the Celery workers through Redis."""

    def __init__(self, settings: Settings) -> None:
        self._app = _app_for(settings.broker_url, settings.celery_queue)

    def enqueue(self, submission_id: int, attempt: int) -> None:
        self._app.send_task(RUN_NEXT, args=[submission_id, attempt])

    def watch(self, submission_id: int, attempt: int) -> None:
        """Ask a worker to take over watching a running attempt's Kubernetes Job."""
        self._app.send_task(WATCH, args=[submission_id, attempt])


@functools.cache
def _app_for(broker_url: str, queue: str) -> Celery:
    celery = Celery("manieval-client", broker=broker_url)
    celery.conf.update(
        task_default_queue=queue,
        task_serializer="json",
        accept_content=["json"],
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=5,
        broker_transport_options={"max_retries": 2},
    )
    return celery
