"""Where a policy comes from and how it is started next to the evaluator.

A source launches the policy as a separate process that connects to the evaluator's endpoint.
`LocalDirectory` runs `policy.py` from a directory with this machine's Python (development and
the demo), in a bubblewrap sandbox when bubblewrap is installed (evaluator/sandbox.py); container
images come with the worker's executors.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Protocol, runtime_checkable

from evaluator import sandbox
from evaluator.results import FailureKind
from evaluator.sandbox import Sandbox
from evaluator.sandbox_command import SandboxLimits

log = logging.getLogger(__name__)

LOG_TAIL_BYTES = 64 * 1024
ECHO_LIMIT_BYTES = 16 * 1024 * 1024
"""Of a policy's output passed on as it comes (`manieval evaluate --policy-output`), the first
this many bytes; of the rest, only the last LOG_TAIL_BYTES, at its end."""
POLICY_ENTRYPOINT = "policy.py"
MAX_SIGNAL = 64
STOP_GRACE_S = 1.0  # a sandboxed policy told to close normally exits well within this


class PolicySourceError(ValueError):
    """The policy source cannot be used (e.g. the directory has no policy.py)."""


class PolicyProcess(Protocol):
    """A running policy: is it alive, what did it print last, stop it."""

    def alive(self) -> bool: ...

    def exit_code(self) -> int | None: ...

    def log_tail(self) -> str: ...

    def exit_detail(self) -> str | None:
        """After stop(): how the policy ended, when the launcher knows more than an exit code."""
        ...

    def stop(self) -> None: ...


@runtime_checkable
class ConfinedProcess(Protocol):
    """A policy process whose launcher enforces resource limits and says which one it hit."""

    def limit_reached(self) -> FailureKind | None: ...


def limit_reached(process: PolicyProcess) -> FailureKind | None:
    """After stop(): the resource limit that ended the policy, when its launcher knows one."""
    return process.limit_reached() if isinstance(process, ConfinedProcess) else None


OutputSink = Callable[[bytes], None]
"""Takes the policy's output (stdout and stderr, interleaved) as it comes, in pieces."""


@runtime_checkable
class EchoingProcess(Protocol):
    """A policy process whose output can be passed on as it comes, not only its tail kept."""

    def echo(self, sink: OutputSink) -> None:
        """Pass everything the policy has printed, and will print, on to `sink` (bounded by
        OutputEcho); `sink` is called on another thread."""
        ...


class OutputEcho:
    """Passes output on as it comes up to `limit` bytes, then keeps only the last
    LOG_TAIL_BYTES, passed on at the end after a line saying how much was left out: a policy
    that prints without end fills no memory, disk or terminal through it."""

    def __init__(self, sink: OutputSink, *, limit: int = ECHO_LIMIT_BYTES) -> None:
        self._sink = sink
        self._room = limit
        self._held = bytearray()
        self._dropped = 0
        self._closed = False

    def feed(self, data: bytes) -> None:
        """Pass `data` on, or hold its end once the limit is reached."""
        if self._closed or not data:
            return
        if self._room > 0:
            passed, data = data[: self._room], data[self._room :]
            self._room -= len(passed)
            self._sink(passed)
        self._held += data
        if len(self._held) > LOG_TAIL_BYTES:
            excess = len(self._held) - LOG_TAIL_BYTES
            del self._held[:excess]
            self._dropped += excess

    def close(self) -> None:
        """The output has ended: pass on what was held back."""
        if self._closed:
            return
        self._closed = True
        if self._held:
            left_out = self._dropped
            note = f"\n[... {left_out} bytes of the policy's output left out ...]\n"
            self._sink((note if left_out else "").encode() + bytes(self._held))


class PolicySource(Protocol):
    """Something that can start a policy which connects to `endpoint`."""

    def describe(self) -> str: ...

    def pinned_image(self) -> str | None:
        """The policy's image, pinned by digest (None: the policy is no image)."""
        ...

    def launch(self, *, endpoint: str, socket_dir: Path) -> PolicyProcess: ...


class LogTail:
    """Drains a stream on a thread, keeping only its last `limit` bytes: spam cannot fill memory."""

    def __init__(self, stream: IO[bytes], *, limit: int = LOG_TAIL_BYTES) -> None:
        self._stream = stream
        self._limit = limit
        self._buffer = bytearray()
        self._lock = threading.Lock()
        self._echo: OutputEcho | None = None
        self._echo_lock = threading.Lock()  # held while passing on: keeps the pieces in order
        self._ended = False
        self.total_bytes = 0
        self._thread = threading.Thread(target=self._drain, daemon=True, name="policy-log")
        self._thread.start()

    def _drain(self) -> None:
        while chunk := self._stream.read1(65536):  # type: ignore[attr-defined]
            with self._echo_lock:
                with self._lock:
                    self.total_bytes += len(chunk)
                    self._buffer += chunk
                    if len(self._buffer) > self._limit:
                        del self._buffer[: len(self._buffer) - self._limit]
                    echo = self._echo
                if echo is not None:
                    echo.feed(chunk)
        with self._echo_lock:
            self._ended = True
            if self._echo is not None:
                self._echo.close()

    def echo(self, sink: OutputSink) -> None:
        """Pass on what was printed so far (what the tail still holds), then the rest as it
        comes (see `EchoingProcess`)."""
        with self._echo_lock:
            with self._lock:
                self._echo = OutputEcho(sink)
                earlier, dropped = bytes(self._buffer), self.total_bytes - len(self._buffer)
            if dropped:
                sink(f"[... {dropped} earlier bytes dropped]\n".encode())
            self._echo.feed(earlier)
            if self._ended:
                self._echo.close()

    def text(self) -> str:
        """The kept tail, decoded leniently."""
        with self._lock:
            data = bytes(self._buffer)
            dropped = self.total_bytes - len(data)
        prefix = f"[... {dropped} earlier bytes dropped]\n" if dropped else ""
        return prefix + data.decode("utf-8", errors="replace")

    def join(self, timeout: float) -> None:
        """Wait for the stream to end (after the process exits)."""
        self._thread.join(timeout)


class LocalProcess:
    """A policy subprocess in its own process group, so stopping it stops its children too; in
    a sandbox, the sandbox's PID namespace holds every descendant and dies with it."""

    def __init__(self, popen: subprocess.Popen[bytes], *, sandbox: Sandbox | None = None) -> None:
        self._popen = popen
        self._sandbox = sandbox
        self._ended: str | None = None
        assert popen.stdout is not None
        self._log = LogTail(popen.stdout)

    def alive(self) -> bool:
        """Whether the process is still running."""
        return self._popen.poll() is None

    def exit_code(self) -> int | None:
        """The exit code, None while running; negative: killed by that signal."""
        code = self._popen.poll()
        if self._sandbox is not None and code is not None and 128 < code <= 128 + MAX_SIGNAL:
            return 128 - code  # bubblewrap reports a signal N as the shell does, 128 + N
        return code

    def log_tail(self) -> str:
        """The last bytes of the policy's stdout and stderr."""
        return self._log.text()

    def echo(self, sink: OutputSink) -> None:
        """Pass the policy's output on to `sink` as it comes (see `EchoingProcess`)."""
        self._log.echo(sink)

    def exit_detail(self) -> str | None:
        """After stop(): the limit the sandbox reached, or how it exited by itself."""
        breach = self._sandbox.watch.breach if self._sandbox is not None else None
        return breach.detail if breach is not None else self._ended

    def limit_reached(self) -> FailureKind | None:
        """After stop(): the kind of the limit the sandbox reached, if it did."""
        breach = self._sandbox.watch.breach if self._sandbox is not None else None
        return breach.kind if breach is not None else None

    def stop(self) -> None:
        """Terminate the process group; kill it if it does not exit within a few seconds."""
        if self._sandbox is not None:
            self._stop_sandbox()
        for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 5.0)):
            if self._popen.poll() is not None:
                break
            try:
                os.killpg(self._popen.pid, sig)
            except ProcessLookupError:
                break
            try:
                self._popen.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        self._log.join(1.0)
        if self._sandbox is not None:
            self._sandbox.cleanup()

    def _stop_sandbox(self) -> None:
        assert self._sandbox is not None
        if self._sandbox.watch.check() is None:  # a last look: a limit reached now still counts
            # The policy was told to close, or has just died: its exit reaches us through
            # bubblewrap's processes, a moment after the evaluator saw the connection end.
            try:
                self._popen.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                pass
            else:
                code = self.exit_code()
                self._ended = None if code == 0 else f"exit code {code}"
        self._sandbox.watch.kill()  # everything in it, wherever its descendants went


@dataclass(frozen=True)
class LocalDirectory:
    """A policy directory with a `policy.py` that calls `manieval_sdk.serve`, run in a sandbox
    when bubblewrap is installed (unconfined otherwise: trusted code only)."""

    path: Path
    limits: SandboxLimits = field(default_factory=SandboxLimits)

    def __post_init__(self) -> None:
        if not (self.path / POLICY_ENTRYPOINT).is_file():
            raise PolicySourceError(f"{self.path} has no {POLICY_ENTRYPOINT}")
        problem = sandbox.unavailable()
        if problem is not None:
            warn_unconfined(problem)

    def describe(self) -> str:
        """How the result document names this policy."""
        return f"dir:{self.path.resolve()}"

    def pinned_image(self) -> None:
        """None: a directory is no image."""
        return None

    def launch(self, *, endpoint: str, socket_dir: Path) -> LocalProcess:
        """Start `python policy.py` with a minimal environment (no secrets of ours leak in)."""
        if sandbox.unavailable() is not None:
            return self._launch_unconfined(endpoint=endpoint, socket_dir=socket_dir)
        started = sandbox.start(
            workdir=self.path,
            entrypoint=POLICY_ENTRYPOINT,
            socket_dir=socket_dir,
            env=sandbox_env(endpoint),
            limits=self.limits,
        )
        return LocalProcess(started.popen, sandbox=started)

    def _launch_unconfined(self, *, endpoint: str, socket_dir: Path) -> LocalProcess:
        env = {
            "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
            "HOME": str(socket_dir),
            "LANG": "C.UTF-8",
            "PYTHONUNBUFFERED": "1",
            "MANIEVAL_ENDPOINT": endpoint,
        }
        popen = subprocess.Popen(
            [sys.executable, POLICY_ENTRYPOINT],
            cwd=self.path,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        return LocalProcess(popen)


@functools.cache
def warn_unconfined(problem: str) -> None:
    """Say once per process that local policies run without a sandbox, and why."""
    log.warning(
        "%s: the policy runs unconfined, as your user, with your files and network", problem
    )


def sandbox_env(endpoint: str) -> dict[str, str]:
    """The whole environment of a sandboxed policy."""
    return {
        "PATH": f"{Path(sys.executable).parent}:/usr/local/bin:/usr/bin:/bin",
        "HOME": "/tmp",
        "LANG": "C.UTF-8",
        "PYTHONUNBUFFERED": "1",
        "PYTHONDONTWRITEBYTECODE": "1",  # its directory is read-only
        "MANIEVAL_ENDPOINT": endpoint,
    }
