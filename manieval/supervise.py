"""A child process the service keeps alive: started in its own process group, restarted when
it dies, stopped by its PID when the service stops.

The embedded registry and Podman's Docker API (:mod:`manieval.engines`) run this way. A PID
file in the data directory lets the next start end a process an earlier run left behind (a
``kill -9`` of the service), and only when its command line is the one this run would start.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

log = logging.getLogger(__name__)

STARTUP_S = 30.0
STOP_GRACE_S = 10.0
CHECK_EVERY_S = 1.0
MAX_BACKOFF_S = 30.0
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # pragma: no cover - runs in the child, before exec
    """A `kill -9` of the service must not leave the child running (Linux only)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


class Supervised:
    """One named child process; `start()` waits until `ready()` says it answers.

    Every spawn happens on the supervisor's own thread, which lives until `stop()`: the child's
    parent-death signal is bound to the thread that forked it.
    """

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        *,
        ready: Callable[[], bool],
        env: dict[str, str] | None = None,
        cwd: Path,
        log_path: Path,
        pid_path: Path,
        startup_s: float = STARTUP_S,
    ) -> None:
        self.name = name
        self.argv = list(argv)
        self.ready = ready
        self.env = env
        self.cwd = cwd
        self.log_path = log_path
        self.pid_path = pid_path
        self.startup_s = startup_s
        self.restarts = 0
        self.problem: str | None = None
        """Why it is not serving now (None: it answers)."""
        self._process: subprocess.Popen[bytes] | None = None
        self._stop = threading.Event()
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._watch, name=f"supervise-{name}", daemon=True)

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def start(self) -> bool:
        """Start and wait until it answers; False (with `problem` set) when it did not."""
        self._end_leftover()
        self._thread.start()
        self._started.wait()
        return self.problem is None

    def stop(self) -> None:
        """Stop watching, then end the child's process group (SIGTERM, then SIGKILL)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=STOP_GRACE_S + 5)
        self._end(self._process)
        self._process = None
        self.pid_path.unlink(missing_ok=True)

    def _watch(self) -> None:
        backoff = 1.0
        self._spawn_until_ready()
        self._started.set()
        while not self._stop.wait(CHECK_EVERY_S):
            process = self._process
            if process is not None and process.poll() is None:
                continue
            code = process.returncode if process is not None else None
            self.problem = f"{self.name} exited ({code}); restarting (log: {self.log_path})"
            log.warning("%s exited with %s; restarting in %.0f s", self.name, code, backoff)
            if self._stop.wait(backoff):
                return
            self.restarts += 1
            if self._spawn_until_ready():
                backoff = 1.0
            else:
                backoff = min(backoff * 2, MAX_BACKOFF_S)

    def _spawn_until_ready(self) -> bool:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        try:
            with self.log_path.open("ab") as out:
                process = subprocess.Popen(
                    self.argv,
                    cwd=self.cwd,
                    env=self.env,
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,  # its own process group: stopped as one
                    preexec_fn=_die_with_parent,  # spawned from the supervisor thread only
                )
        except OSError as exc:
            self.problem = f"{self.name} could not start: {exc}"
            return False
        self._process = process
        self.pid_path.write_text(f"{process.pid}\n")
        deadline = time.monotonic() + self.startup_s
        while time.monotonic() < deadline and not self._stop.is_set():
            if process.poll() is not None:
                self.problem = (
                    f"{self.name} exited at start ({process.returncode}): {self._log_tail()}"
                )
                return False
            if self._answers():
                self.problem = None
                log.info("%s is up (pid %s)", self.name, process.pid)
                return True
            time.sleep(0.1)
        self.problem = f"{self.name} did not answer within {self.startup_s:.0f} s"
        self._end(process)
        return False

    def _answers(self) -> bool:
        try:
            return self.ready()
        except Exception:  # a probe that fails in any way means "not yet"
            return False

    def _log_tail(self) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return "(no log)"
        return lines[-1][-300:] if lines else "(no output)"

    def _end(self, process: subprocess.Popen[bytes] | None) -> None:
        if process is None or process.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()

    def _end_leftover(self) -> None:
        """An earlier run's child, still alive after that run died: end it, if it is ours."""
        try:
            pid = int(self.pid_path.read_text().strip())
        except (OSError, ValueError):
            return
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            self.pid_path.unlink(missing_ok=True)
            return
        if [part.decode(errors="replace") for part in cmdline if part] != self.argv:
            self.pid_path.unlink(missing_ok=True)  # the PID was reused by something else
            return
        log.warning("ending %s (pid %s) left by an earlier run", self.name, pid)
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        while time.monotonic() < deadline and Path(f"/proc/{pid}").exists():
            time.sleep(0.1)
        if Path(f"/proc/{pid}").exists():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(pid, signal.SIGKILL)
        self.pid_path.unlink(missing_ok=True)
