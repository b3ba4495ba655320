"""The service in one process: the server in uvicorn and, on the embedded default, its worker.

The embedded worker is the same worker as a Celery one: it reaches the server over HTTP on
the loopback address with the worker token, through ``/internal/v1``. `manieval serve` and
`manieval demo` run this; with ``MANIEVAL_QUEUE=celery`` only the server runs here.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType

import uvicorn
from sqlalchemy.orm import Session, sessionmaker

from manieval.engines import Engines
from server.app import create_app
from server.kit.db import make_engine, session_factory
from server.kit.settings import Settings
from server.submissions.images import image_resolver
from server.submissions.service import ImageGate
from server.submissions.work import end_stopped
from worker.embedded import EmbeddedWorker, evaluating_threads
from worker.settings import WorkerSettings

log = logging.getLogger(__name__)

EMBEDDED_WORKER = "embedded"
WORKER_STOP_S = 20.0
"""How long a stop waits for the evaluations in flight (each stops within about a second)."""
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def embedded_worker_settings(
    settings: Settings, *, port: int, engine_url: str | None = None
) -> WorkerSettings:
    """The embedded worker's settings: the environment's, pointed at this server (and at the
    engine the service started, when it started one)."""
    worker = WorkerSettings(
        server_url=f"http://127.0.0.1:{port}",
        worker_token=settings.secret("worker_token"),  # type: ignore[arg-type]
        worker_name=EMBEDDED_WORKER,
        data_dir=settings.data_dir,
        allow_local_policies=settings.allow_local_policies,
        policy_gpus=settings.policy_gpus,  # what the server promises, its worker gives
    )
    if worker.evaluation_processes == 0:  # never in the server's process: it would share its GIL
        worker = worker.model_copy(update={"evaluation_processes": 1})
    if engine_url is None:
        return worker
    return worker.model_copy(update={"docker_engine_url": engine_url})


class _Server(uvicorn.Server):
    """uvicorn, whose stop signal (Ctrl-C, SIGTERM) first stops what runs next to it.

    The server keeps answering while `before_exit` stops the evaluations in flight, so their
    last requests land; then it shuts down. A second Ctrl-C stops it at once.
    """

    def __init__(self, config: uvicorn.Config, *, before_exit: Callable[[], None]) -> None:
        super().__init__(config)
        self._before_exit = before_exit
        self._stopping: threading.Thread | None = None

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        # uvicorn's own raises the signal again after its shutdown: SIGTERM's default action
        # would end the process before the service stopped its engines, and SIGINT would exit
        # 130 through a KeyboardInterrupt. The service ends by itself, with 0, once stopped.
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        original = {sig: signal.signal(sig, self.handle_exit) for sig in STOP_SIGNALS}
        try:
            yield
        finally:
            for sig, handler in original.items():
                signal.signal(sig, handler)

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if self._stopping is None:
            # Not in the signal handler: the event loop it interrupts serves the worker.
            self._stopping = threading.Thread(
                target=self._stop_then_exit, name="manieval-stop", daemon=True
            )
            self._stopping.start()
        else:
            self.should_exit = True
            self.force_exit = sig == signal.SIGINT

    def _stop_then_exit(self) -> None:
        try:
            self._before_exit()
        finally:
            self.should_exit = True


class Service:
    """`start()` in a thread (demo, tests) or `run()` in the foreground (serve).

    With `engines` (serve, demo) the registry and the container engine start first, are
    supervised while the server runs, and stop after it; image submissions are refused, with
    the reason, while they are missing or down.

    A stop (Ctrl-C, SIGTERM, `stop()`) goes in this order: the embedded worker interrupts the
    evaluations in flight (their policy processes and containers removed), the server records
    them as interrupted and queues them again (no quota used, runs again at the next start),
    the server shuts down, then the engines stop.
    """

    def __init__(
        self,
        settings: Settings,
        *,
        host: str = "127.0.0.1",
        port: int = 8000,
        sessions: sessionmaker[Session] | None = None,
        engines: Engines | None = None,
    ) -> None:
        self.url = f"http://{host}:{port}"
        self.engines = engines
        self.worker: EmbeddedWorker | None = None
        resolve = None
        if engines is not None:
            settings = engines.server_settings()
            resolve = ImageGate(image_resolver(settings), engines.refusal)
        self.settings = settings
        self.sessions = sessions or session_factory(make_engine(settings.resolved_database_url))
        self.interrupted: list[int] = []
        """Submissions the last stop interrupted (queued again)."""
        self._work_lock = threading.Lock()
        self._work_stopped = False
        if settings.queue == "inline":
            worker_settings = embedded_worker_settings(
                settings, port=port, engine_url=engines.engine_url if engines else None
            )
            self.worker = EmbeddedWorker(worker_settings, threads=settings.inline_workers)
        app = create_app(
            settings,
            sessions=self.sessions,
            work=self.worker.queue if self.worker else None,
            resolve=resolve,
        )
        self.server = _Server(
            uvicorn.Config(
                app,
                host=host,
                port=port,
                log_config=None,
                proxy_headers=True,
                timeout_graceful_shutdown=5,  # open live streams must not hold a Ctrl-C
            ),
            before_exit=self.stop_work,
        )
        self._thread: threading.Thread | None = None
        self._worker_thread = threading.Thread(
            target=self._start_worker, name="manieval-embedded-start", daemon=True
        )

    def start_engines(self) -> list[str]:
        """Start the registry and the engine (when the service has them); their problems."""
        return self.engines.start() if self.engines is not None else []

    def run(self) -> None:
        """Serve until interrupted (Ctrl-C, SIGTERM), then stop everything and return; start
        `start_engines()` first."""
        self._worker_thread.start()
        try:
            # The stop signals are ours from here, not only once uvicorn's loop runs: a Ctrl-C
            # while the loop is being built stops as cleanly as one a second later (it used to
            # raise inside the loop's constructor, whose half-made loop then failed to close).
            with self.server.capture_signals():
                self.server.run()
        finally:
            if not self.server.force_exit:  # a second Ctrl-C: `end_process` ends what runs
                self.stop_work()  # done already when a signal stopped the server
            self._stop_engines()

    def start(self) -> bool:
        """Serve in a thread; False when the server could not start (the port is taken)."""
        self._thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)
        self._thread.start()
        while not self.server.started:
            if not self._thread.is_alive():
                self._stop_engines()
                return False
            time.sleep(0.05)
        self._worker_thread.start()
        return True

    def wait(self) -> None:
        """Until the server stops (started with `start()`)."""
        if self._thread is not None:
            self._thread.join()

    def stop(self) -> None:
        """Stop the evaluations in flight (recorded, queued again), the server, the engines."""
        self.stop_work()
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=30)
        self._stop_engines()

    def stop_work(self) -> None:
        """Interrupt the embedded worker's evaluations and record them as interrupted: `error`
        of ours (no quota), queued again (`interrupted`); once, whoever calls first."""
        with self._work_lock:
            if self._work_stopped:
                return
            self._work_stopped = True
            if self.worker is None:
                return
            if not self.worker.stop(timeout=WORKER_STOP_S):
                log.warning("an evaluation did not stop within %.0f s", WORKER_STOP_S)
            if not self.worker.started:
                return  # it claimed nothing: what a crashed run left is for the next start
            self._remove_policy_containers()
            try:
                with self.sessions.begin() as db:
                    self.interrupted = end_stopped(db, worker=self.worker.settings.worker_name)
            except Exception:  # the database is down: the next start ends them (run again once)
                log.exception("the interrupted evaluations could not be recorded")
                return
            if self.interrupted:
                log.info("submissions %s interrupted: queued again", self.interrupted)

    def _remove_policy_containers(self) -> None:
        """Each stopped evaluation removes its policy's container itself; whatever one left
        (an engine too slow to answer its removal, say) goes now, while the engine still runs,
        not at the reconciler's first pass after the next start."""
        assert self.worker is not None
        settings = self.worker.settings
        if settings.docker_engine_url is None:
            return
        from docker.errors import DockerException

        from worker.containers import engine, remove_leftovers

        try:
            client = engine(settings.docker_engine_url)
            try:
                left = remove_leftovers(client, service=settings.service_id, keep=set(), grace_s=0)
            finally:
                client.close()
        except DockerException as exc:  # the reconciler of the next start removes them
            log.warning("the policy containers could not be listed for removal: %s", exc)
            return
        if left:
            log.warning("removed policy containers the stopped evaluations left: %s", left)

    def _stop_engines(self) -> None:
        if self.engines is not None:
            self.engines.stop()

    def _start_worker(self) -> None:
        if self.worker is None:
            return
        while not self.server.started and not self.server.should_exit:
            time.sleep(0.05)
        if not self.server.should_exit:
            self.worker.start()


def end_process(code: int) -> None:
    """Return when the process may exit normally; else flush and end it now with `code`.

    An evaluation that outlived the stop (`WORKER_STOP_S`) may still be inside SAPIEN or torch:
    the interpreter's exit would then destroy their running C++ threads and abort the process
    (``terminate called without an active exception``, exit 134). Everything of ours is done
    by now (the database committed, the engines stopped), so `os._exit` loses nothing but
    that thread; its policy process ends with us (bubblewrap's ``--die-with-parent``) and the
    next start's reconciler removes a container it leaves.
    """
    stuck = evaluating_threads()
    if not stuck:
        return
    log.warning("%s still evaluating after the stop: ending the process", ", ".join(stuck))
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed or broken stream: nothing to keep
            stream.flush()
    os._exit(code)
