"""The embedded queue: worker threads inside the server process (`MANIEVAL_QUEUE=inline`)."""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


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
