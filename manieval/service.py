"""The service in one process: the server in uvicorn and, on the embedded default, its worker.

The embedded worker is the same worker as a Celery one: it reaches the server over HTTP on
the loopback address with the worker token, through ``/internal/v1``. `manieval serve` and
`manieval demo` run this; with ``MANIEVAL_QUEUE=celery`` only the server runs here.
"""

from __future__ import annotations

import threading
import time

import uvicorn
from sqlalchemy.orm import Session, sessionmaker

from manieval.engines import Engines
from server.app import create_app
from server.kit.settings import Settings
from server.submissions.images import image_resolver
from server.submissions.service import ImageGate
from worker.embedded import EmbeddedWorker
from worker.settings import WorkerSettings

EMBEDDED_WORKER = "embedded"


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
    )
    if engine_url is None:
        return worker
    return worker.model_copy(update={"docker_engine_url": engine_url})


class Service:
    """`start()` in a thread (demo, tests) or `run()` in the foreground (serve).

    With `engines` (serve, demo) the registry and the container engine start first, are
    supervised while the server runs, and stop after it; image submissions are refused, with
    the reason, while they are missing or down.
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
        if settings.queue == "inline":
            worker_settings = embedded_worker_settings(
                settings, port=port, engine_url=engines.engine_url if engines else None
            )
            self.worker = EmbeddedWorker(worker_settings, threads=settings.inline_workers)
        app = create_app(
            settings,
            sessions=sessions,
            work=self.worker.queue if self.worker else None,
            resolve=resolve,
        )
        self.server = uvicorn.Server(
            uvicorn.Config(
                app,
                host=host,
                port=port,
                log_config=None,
                proxy_headers=True,
                timeout_graceful_shutdown=5,  # open live streams must not hold a Ctrl-C
            )
        )
        self._thread: threading.Thread | None = None
        self._worker_thread = threading.Thread(
            target=self._start_worker, name="manieval-embedded-start", daemon=True
        )

    def start_engines(self) -> list[str]:
        """Start the registry and the engine (when the service has them); their problems."""
        return self.engines.start() if self.engines is not None else []

    def run(self) -> None:
        """Serve until interrupted (Ctrl-C, SIGTERM); start `start_engines()` first."""
        self._worker_thread.start()
        try:
            self.server.run()
        finally:
            self._stop_worker()
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
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=30)
        self._stop_worker()
        self._stop_engines()

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

    def _stop_worker(self) -> None:
        if self.worker is not None:
            self.worker.stop(timeout=5)
