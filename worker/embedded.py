"""The embedded worker: threads inside the server's process (`MANIEVAL_QUEUE=inline`) that
take wake-ups from an in-memory queue and reach the server through ``/internal/v1``."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

from worker.reconcile import reconcile_pass, runtime_cleaners
from worker.run import run_next
from worker.server_api import ServerAPI, ServerUnavailable
from worker.settings import WorkerSettings
from worker.spool_sender import resend_pass

log = logging.getLogger(__name__)
RECONCILE_EVERY_S = 30.0
THREAD_PREFIX = "manieval-worker-"


def evaluating_threads() -> list[str]:
    """The names of this process's embedded-worker threads still alive (after a stop: ones
    still inside an evaluation)."""
    return [t.name for t in threading.enumerate() if t.name.startswith(THREAD_PREFIX)]


class InlineQueue:
    """The embedded default: worker threads in the server process run attempts in order.

    Each evaluation runs its policy and simulator in child processes, so threads here only
    wait; `threads` is how many evaluations run at once (one per core is sensible).
    """

    def __init__(self, run: Callable[[int, int], object], *, threads: int = 1) -> None:
        self._run = run
        self._queue: queue.Queue[tuple[int, int] | None] = queue.Queue()
        self._threads = [
            threading.Thread(target=self._loop, name=f"{THREAD_PREFIX}{i}", daemon=True)
            for i in range(threads)
        ]
        self.started = False
        self._busy = 0
        self._lock = threading.Lock()
        self.idle = threading.Event()
        self.idle.set()

    def start(self) -> None:
        if not self.started:
            self.started = True
            for thread in self._threads:
                thread.start()

    def enqueue(self, submission_id: int, attempt: int) -> None:
        with self._lock:
            self.idle.clear()
            self._queue.put((submission_id, attempt))

    def stop(self, timeout: float | None = None) -> bool:
        """Let the threads finish what they run; True when all have (within `timeout` in all)."""
        if self.started:
            for _ in self._threads:
                self._queue.put(None)
            _join(self._threads, timeout)
        return not any(thread.is_alive() for thread in self._threads)

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


class EmbeddedWorker:
    """The embedded default's worker: threads in the server's process that reach the server
    through ``/internal/v1``, exactly as a Celery worker on another machine does.

    `queue` is the server's work queue (its outbox sends wake-ups into it); `start()` once the
    server answers: it sends what an earlier run kept in the spool, ends the attempts that died
    with that run (they run again once), then drains the queue, and reconciles and tries its
    spool again every 30 s.
    `stop()` interrupts the evaluations in flight and leaves them for its caller to record
    (the service queues them again: `server.submissions.work.end_stopped`).
    """

    def __init__(self, settings: WorkerSettings, *, threads: int = 1) -> None:
        self.settings = settings
        self.queue = InlineQueue(self._drain, threads=threads)
        self._api: ServerAPI | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()  # start() and stop() may come from different threads
        self._starting = False
        self._timer = threading.Thread(
            target=self._reconcile, name="manieval-reconcile", daemon=True
        )

    @property
    def started(self) -> bool:
        """Whether it has claimed work, or could have (stopped since or not)."""
        return self.queue.started

    def start(self, api: ServerAPI | None = None) -> None:
        """Connect (`api`: tests hand one over an in-process transport) and start working;
        nothing once stopped."""
        with self._lock:
            if self._stop.is_set():
                return
            self._api = api or ServerAPI.connect(self.settings)
            self._api.stop = self._stop
            self._starting = True
        try:
            self._api.flush_spool()
            ended = self._api.restarted(self.settings.worker_name)
        except ServerUnavailable:
            if not self._stop.is_set():
                raise
            ended = []  # stopped while starting: the next start tells the server
        finally:
            with self._lock:
                self._starting = False
        if ended:
            log.info("submissions %s were running when the server stopped: queued again", ended)
        with self._lock:
            if self._stop.is_set():  # stop() left the client to us
                self._api.close()
                return
            self.queue.start()
            self.queue.enqueue(0, 0)  # whatever waits already
            self._timer.start()

    def stop(self, timeout: float | None = None) -> bool:
        """Interrupt what runs (each evaluation stops within about a second, its policy process
        or container gone, and is not reported) and wait up to `timeout` for the threads; True
        when they all ended."""
        with self._lock:
            self._stop.set()
        deadline = None if timeout is None else time.monotonic() + timeout
        finished = self.queue.stop(timeout)
        if self._timer.is_alive():
            _join([self._timer], None if deadline is None else deadline - time.monotonic())
        # A thread still evaluating (or starting) keeps the client until the process ends:
        # closed under it, its last requests would fail with an error of ours.
        with self._lock:
            if self._api is not None and finished and not self._starting:
                self._api.close()
        return finished

    @property
    def api(self) -> ServerAPI:
        assert self._api is not None, "start() first"
        return self._api

    def _drain(self, _sid: int, _attempt: int) -> None:
        # A message is a wake-up: run the fairest queued submissions until none can be claimed.
        while not self._stop.is_set() and run_next(self.api, self.settings) is not None:
            pass

    def _reconcile(self) -> None:
        cleaners = runtime_cleaners(self.settings)
        while not self._stop.wait(RECONCILE_EVERY_S):
            try:
                reconcile_pass(self.api, cleaners=cleaners)
                resend_pass(self.api)  # what a long outage left in the spool
            except Exception:
                log.exception("reconciling failed; the next pass will try again")


def _join(threads: list[threading.Thread], timeout: float | None) -> None:
    """Join each thread, all within `timeout` (None: without limit)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    for thread in threads:
        thread.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
