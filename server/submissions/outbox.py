"""From the outbox to the queue: work is sent only after the transaction that created it.

``Dispatcher.dispatch()`` sends every unsent outbox row and marks it sent; it runs right after
each commit that wrote one (the after-commit kick) and periodically (the sweep), so a crash or a
broker outage between the commit and the send delays the work but never loses it.
"""

from __future__ import annotations

import functools
import logging
import threading
from typing import Protocol

from celery import Celery
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from internal_api.tasks import RUN_NEXT
from server.models import Outbox, utcnow

log = logging.getLogger(__name__)


class WorkQueue(Protocol):
    def enqueue(self, submission_id: int, attempt: int) -> None:
        """Hand one attempt to the workers; may raise if the broker is unreachable."""


class Dispatcher:
    def __init__(self, sessions: sessionmaker[Session], work: WorkQueue) -> None:
        self._sessions = sessions
        self._work = work
        self._lock = threading.Lock()

    @property
    def work(self) -> WorkQueue:
        return self._work

    def dispatch(self, batch: int = 100) -> int:
        """Send pending rows in order; returns how many were sent. Never raises."""
        sent = 0
        with self._lock:  # one dispatch at a time per process; rows are locked across processes
            while True:
                try:
                    n = self._dispatch_batch(batch)
                except NotAttached:  # expected until `manieval serve` attaches its worker
                    log.debug("no worker attached yet: work stays in the outbox")
                    return sent
                except Exception:
                    log.exception("dispatching queued work failed; the sweep will retry")
                    return sent
                sent += n
                if n < batch:
                    return sent

    def _dispatch_batch(self, batch: int) -> int:
        with self._sessions.begin() as db:
            rows = db.scalars(
                select(Outbox)
                .where(Outbox.sent_at.is_(None))
                .order_by(Outbox.id)
                .limit(batch)
                .with_for_update(skip_locked=True)
            ).all()
            for row in rows:
                self._work.enqueue(row.submission_id, row.attempt)
                row.sent_at = utcnow()
            return len(rows)


class CeleryQueue:
    """Wake-ups to the Celery workers through the broker, by task name: the server never
    imports the worker."""

    def __init__(self, broker_url: str, queue: str) -> None:
        self._app = _celery_for(broker_url, queue)

    def enqueue(self, submission_id: int, attempt: int) -> None:
        self._app.send_task(RUN_NEXT, args=[submission_id, attempt])


class NotAttached(RuntimeError):
    """No worker is attached to this server yet."""


class Unattached:
    """The embedded default before its worker is attached (`manieval serve` attaches it):
    work stays in the outbox until then."""

    def enqueue(self, submission_id: int, attempt: int) -> None:
        raise NotAttached("no worker is attached to this server yet")


@functools.cache
def _celery_for(broker_url: str, queue: str) -> Celery:
    celery = Celery("manieval-server", broker=broker_url)
    celery.conf.update(
        task_default_queue=queue,
        task_serializer="json",
        accept_content=["json"],
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=5,
        broker_transport_options={"max_retries": 2},
    )
    return celery
