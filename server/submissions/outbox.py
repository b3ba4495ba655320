"""From the outbox to the queue: work is sent only after the transaction that created it.

``Dispatcher.dispatch()`` sends every unsent outbox row and marks it sent; it runs right after
each commit that wrote one (the after-commit kick) and periodically (the sweep), so a crash or a
broker outage between the commit and the send delays the work but never loses it.
"""

from __future__ import annotations

import logging
import threading
from typing import Protocol

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

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

    def dispatch(self, batch: int = 100) -> int:
        """Send pending rows in order; returns how many were sent. Never raises."""
        sent = 0
        with self._lock:  # one dispatch at a time per process; rows are locked across processes
            while True:
                try:
                    n = self._dispatch_batch(batch)
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
