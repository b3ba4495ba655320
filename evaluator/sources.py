"""Where a policy comes from and how it is started next to the evaluator.

A source launches the policy as a separate process that connects to the evaluator's endpoint.
`LocalDirectory` runs `policy.py` from a directory with this machine's Python (development and
the demo); container images come with the worker's executors.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Protocol

LOG_TAIL_BYTES = 64 * 1024
POLICY_ENTRYPOINT = "policy.py"


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


class PolicySource(Protocol):
    """Something that can start a policy which connects to `endpoint`."""

    def describe(self) -> str: ...

    def launch(self, *, endpoint: str, socket_dir: Path) -> PolicyProcess: ...


class LogTail:
    """Drains a stream on a thread, keeping only its last `limit` bytes: spam cannot fill memory."""

    def __init__(self, stream: IO[bytes], *, limit: int = LOG_TAIL_BYTES) -> None:
        self._stream = stream
        self._limit = limit
        self._buffer = bytearray()
        self._lock = threading.Lock()
        self.total_bytes = 0
        self._thread = threading.Thread(target=self._drain, daemon=True, name="policy-log")
        self._thread.start()

    def _drain(self) -> None:
        while chunk := self._stream.read1(65536):  # type: ignore[attr-defined]
            with self._lock:
                self.total_bytes += len(chunk)
                self._buffer += chunk
                if len(self._buffer) > self._limit:
                    del self._buffer[: len(self._buffer) - self._limit]

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
    """A policy subprocess in its own process group, so stopping it stops its children too."""

    def __init__(self, popen: subprocess.Popen[bytes]) -> None:
        self._popen = popen
        assert popen.stdout is not None
        self._log = LogTail(popen.stdout)

    def alive(self) -> bool:
        """Whether the process is still running."""
        return self._popen.poll() is None

    def exit_code(self) -> int | None:
        """The exit code, None while running."""
        return self._popen.poll()

    def log_tail(self) -> str:
        """The last bytes of the policy's stdout and stderr."""
        return self._log.text()

    def exit_detail(self) -> str | None:
        """Nothing beyond the exit code."""
        return None

    def stop(self) -> None:
        """Terminate the process group; kill it if it does not exit within a few seconds."""
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


@dataclass(frozen=True)
class LocalDirectory:
    """A policy directory with a `policy.py` that calls `manieval_sdk.serve` (trusted code only)."""

    path: Path

    def __post_init__(self) -> None:
        if not (self.path / POLICY_ENTRYPOINT).is_file():
            raise PolicySourceError(f"{self.path} has no {POLICY_ENTRYPOINT}")

    def describe(self) -> str:
        """How the result document names this policy."""
        return f"dir:{self.path.resolve()}"

    def launch(self, *, endpoint: str, socket_dir: Path) -> LocalProcess:
        """Start `python policy.py` with a minimal environment (no secrets of ours leak in)."""
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
