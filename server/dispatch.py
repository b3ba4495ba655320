"""From the outbox to the queue: work is sent only after the transaction that created it.

``Dispatcher.dispatch()`` sends every unsent outbox row and marks it sent; it runs right after
each commit that wrote one (the after-commit kick) and periodically (the sweep), so a crash or a
broker outage between the commit and the send delays the work but never loses it.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
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


class InlineQueue:
    """The embedded default: worker threads in the server process run attempts in order.

    Each evaluation runs its policy and simulator in child processes, so threads here only
    wait; `threads` is how many evaluations run at once (one per core is sensible).
    """

    def __init__(self, run: Callable[[int, int], object], *, threads: int = 1) -> None:
        self._run = run
        self._queue: queue.Queue[tuple[int, int] | None] = queue.Queue()
        self._threads = [
            threading.Thread(target=self._loop, name=f"manieval-worker-{i}", daemon=True)
            for i in range(threads)
        ]
        self._started = False
        self._busy = 0
        self._lock = threading.Lock()
        self.idle = threading.Event()
        self.idle.set()

    def start(self) -> None:
        if not self._started:
            self._started = True
            for thread in self._threads:
                thread.start()

    def enqueue(self, submission_id: int, attempt: int) -> None:
        with self._lock:
            self.idle.clear()
            self._queue.put((submission_id, attempt))

    def stop(self, timeout: float | None = None) -> None:
        if self._started:
            for _ in self._threads:
                self._queue.put(None)
            for thread in self._threads:
                thread.join(timeout)

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            with self._lock:
                self._busy += 1
            try:
                self._run(*item)
            except Exception:
                log.exception("running submission %s attempt %s failed", *item)
            finally:
                with self._lock:
                    self._busy -= 1
                    if self._busy == 0 and self._queue.empty():
                        self.idle.set()
