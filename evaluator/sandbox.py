"""Start a local policy in a bubblewrap sandbox, watch what it uses, and stop it at a limit.

The command line and mount plan live in evaluator/sandbox_command.py; this module gathers what
they need from the host (the Python runtime, the system's layout), starts bubblewrap, and watches
the running sandbox. The kernel's limits cap each process; the watcher samples what the sandbox
uses in total and stops it when it reaches a limit, so that the evaluation ends with a failure
that names it (`process_limit`, `memory_limit`, `file_size_limit`) instead of a timeout or a
protocol error.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from evaluator.limits import (
    SANDBOX,
    Breach,
    memory_breach,
    process_breach,
    scratch_breach,
)
from evaluator.sandbox_command import (
    GROUP,
    MIB,
    OUTER_ENV,
    PASSWD,
    SANDBOX_GID,
    SCRATCH_DIRS,
    SandboxLimits,
    SandboxSpec,
    bwrap_command,
    staged_command,
)

WATCH_INTERVAL_S = 0.2
SYSTEM_TREES = ("/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32")
RUNTIME_MODULES = ("manieval_sdk", "numpy", "msgpack")


def unavailable() -> str | None:
    """Why policies cannot be sandboxed on this machine, or None when they can."""
    if shutil.which("bwrap") is None:
        return "bubblewrap (bwrap) is not installed"
    if os.geteuid() == 0:
        missing = [tool for tool in ("unshare", "setpriv", "mount") if shutil.which(tool) is None]
        if missing:
            return f"{', '.join(missing)} (util-linux) not found"
    return None


@dataclass(frozen=True)
class PythonRuntime:
    """What the policy's Python needs from the host, outside the system's directories."""

    paths: tuple[Path, ...]  # to see read-only: the installation, virtualenv, SDK...
    pythonpath: tuple[Path, ...]  # import roots the interpreter would not search by itself


def python_runtime() -> PythonRuntime:
    """This interpreter's installation and virtualenv, and where the SDK, numpy and msgpack are
    imported from: a site-packages of the installation, an import hook's directory (an editable
    install lives in the source tree), or a PYTHONPATH or user site-packages entry."""
    installed = [Path(p) for p in (sys.base_prefix, sys.base_exec_prefix, sys.prefix)]
    paths = [*installed, Path(os.path.realpath(sys.executable)).parent]
    search = {Path(os.path.abspath(entry)) for entry in sys.path if entry}
    pythonpath: list[Path] = []
    for name in RUNTIME_MODULES:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            continue
        origin = Path(spec.origin)
        location = origin.parent if spec.submodule_search_locations else origin
        if location.parent not in search:  # found by an import hook, which still finds it
            paths.append(location if location.is_dir() else location.parent)
        elif not any(location.is_relative_to(prefix) for prefix in installed):
            paths.append(location.parent)
            if location.parent not in pythonpath:
                pythonpath.append(location.parent)
    system = [Path(tree) for tree in SYSTEM_TREES]
    return PythonRuntime(minimal_cover(paths, covered=system), tuple(pythonpath))


def minimal_cover(paths: Sequence[Path], *, covered: Sequence[Path] = ()) -> tuple[Path, ...]:
    """`paths` without duplicates and without those inside another path or inside `covered`."""
    kept: list[Path] = []
    for path in sorted(set(paths), key=lambda p: len(p.parts)):
        if not any(path.is_relative_to(outer) for outer in (*covered, *kept)):
            kept.append(path)
    return tuple(kept)


def system_layout() -> tuple[tuple[str, str | None], ...]:
    """The system trees that exist here: merged-/usr systems have /bin, /lib... as symlinks."""
    layout: list[tuple[str, str | None]] = []
    for tree in SYSTEM_TREES:
        if os.path.islink(tree):
            layout.append((tree, os.readlink(tree)))
        elif os.path.isdir(tree):
            layout.append((tree, None))
    return tuple(layout)


@dataclass(frozen=True)
class Usage:
    """What a sandbox uses at one moment."""

    tasks: int  # processes and threads
    memory_bytes: int  # proportional set size, summed over its processes
    full_scratch: str | None  # a scratch directory with no space left


def breached(usage: Usage, limits: SandboxLimits) -> Breach | None:
    """Which limit `usage` has reached, if any."""
    if usage.tasks >= limits.processes:
        return process_breach(SANDBOX, limits.processes)
    if usage.memory_bytes >= limits.memory_mib * MIB:
        return memory_breach(SANDBOX, limits.memory_mib)
    if usage.full_scratch is not None:
        return scratch_breach(SANDBOX, usage.full_scratch, limits.scratch_mib)
    return None


def measure(root: Path) -> Usage:
    """Sample the sandbox whose root directory is `root` (/proc/PID/root of its first process)."""
    proc = root / "proc"  # the sandbox's own /proc: its processes and nothing else
    tasks = memory = 0
    for entry in os.scandir(proc):
        if not entry.name.isdigit():
            continue
        try:
            tasks += _kib_field(proc / entry.name / "status", "Threads:")
            memory += _kib_field(proc / entry.name / "smaps_rollup", "Pss:") * 1024
        except (OSError, ValueError):  # it exited meanwhile, or is a zombie without memory
            continue
    full = next(
        (path for path in SCRATCH_DIRS if os.statvfs(root / path.lstrip("/")).f_bavail == 0),
        None,
    )
    return Usage(tasks=tasks, memory_bytes=memory, full_scratch=full)


def _kib_field(path: Path, name: str) -> int:
    for line in path.read_text().splitlines():
        if line.startswith(name):
            return int(line.split()[1])
    raise ValueError(f"no {name} in {path}")


class SandboxWatch:
    """Samples a running sandbox and kills it when it reaches a limit, remembering which."""

    def __init__(self, info: IO[bytes], limits: SandboxLimits) -> None:
        self._info = info
        self._limits = limits
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        self._pid: int | None = None
        self._pidns: int | None = None
        self._pidfd: int | None = None
        self.breach: Breach | None = None
        self._thread = threading.Thread(target=self._run, daemon=True, name="sandbox-watch")
        self._thread.start()

    def _run(self) -> None:
        # bwrap writes the sandbox's first process (its PID 1) to the info pipe, then closes it.
        with self._info:
            raw = self._info.read()
        try:
            info = json.loads(raw)
            pid, pidns = int(info["child-pid"]), int(info["pid-namespace"])
            pidfd = os.pidfd_open(pid)
        except (ValueError, KeyError, TypeError, OSError):
            return  # bwrap failed before starting the sandbox; its log says why
        with self._lock:
            if self._stopped.is_set():
                os.close(pidfd)
                return
            self._pid, self._pidns, self._pidfd = pid, pidns, pidfd
        while not self._stopped.wait(WATCH_INTERVAL_S):
            if self.check() is not None:
                return

    def check(self) -> Breach | None:
        """Sample now; on reaching a limit, kill the sandbox. Returns the first breach seen."""
        with self._lock:
            if self.breach is not None or self._pid is None:
                return self.breach
            try:
                if os.stat(f"/proc/{self._pid}/ns/pid").st_ino != self._pidns:
                    return None  # the sandbox is gone and its PID was reused
                usage = measure(Path(f"/proc/{self._pid}/root"))
            except OSError:
                return None  # the sandbox ended while we looked
            self.breach = breached(usage, self._limits)
            if self.breach is not None:
                self._kill()
            return self.breach

    def kill(self) -> None:
        """Kill every process in the sandbox (the kernel empties a PID namespace with its PID 1)."""
        with self._lock:
            self._kill()

    def _kill(self) -> None:
        if self._pidfd is not None:
            try:
                signal.pidfd_send_signal(self._pidfd, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def close(self) -> None:
        """Stop watching and release the process handle."""
        self._stopped.set()
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)
        with self._lock:
            if self._pidfd is not None:
                os.close(self._pidfd)
                self._pidfd = None
            self._pid = None


@dataclass
class Sandbox:
    """A started sandbox: its outermost process, its watcher, and what to remove after it."""

    popen: subprocess.Popen[bytes]
    watch: SandboxWatch
    stage: Path | None

    def cleanup(self) -> None:
        """Release the watcher and the staging directory (empty outside its mount namespace)."""
        self.watch.close()
        if self.stage is not None:
            try:
                self.stage.rmdir()
            except OSError:
                pass


def start(
    *,
    workdir: Path,
    entrypoint: str,
    socket_dir: Path,
    env: Mapping[str, str],
    limits: SandboxLimits,
) -> Sandbox:
    """Start `python entrypoint` from `workdir` in a new sandbox, output to a pipe."""
    bwrap = shutil.which("bwrap")
    assert bwrap is not None, "check unavailable() first"
    info_read, info_write = os.pipe()
    passwd_fd, group_fd = _data_fd(PASSWD), _data_fd(GROUP)
    root = os.geteuid() == 0
    stage = Path(tempfile.mkdtemp(prefix="manieval-stage-")) if root else None
    runtime = python_runtime()
    if runtime.pythonpath:
        env = {**env, "PYTHONPATH": os.pathsep.join(str(path) for path in runtime.pythonpath)}
    spec = SandboxSpec(
        bwrap=bwrap,
        python=sys.executable,
        entrypoint=entrypoint,
        workdir=workdir.resolve(),
        socket_dir=socket_dir.resolve(),
        runtime=runtime.paths,
        system=system_layout(),
        env=env,
        limits=limits,
        info_fd=info_write,
        passwd_fd=passwd_fd,
        group_fd=group_fd,
        stage=stage,
    )
    if stage is not None:
        os.chmod(stage, 0o755)
        share_socket_dir(socket_dir)
        command = staged_command(spec, unshare=_tool("unshare"), setpriv=_tool("setpriv"))
    else:
        command = bwrap_command(spec)
    try:
        popen = subprocess.Popen(
            command,
            cwd="/",
            env=OUTER_ENV,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            pass_fds=(info_write, passwd_fd, group_fd),
        )
    except BaseException:
        os.close(info_read)
        if stage is not None:
            stage.rmdir()
        raise
    finally:
        for fd in (info_write, passwd_fd, group_fd):
            os.close(fd)
    return Sandbox(popen, SandboxWatch(os.fdopen(info_read, "rb"), limits), stage)


def share_socket_dir(socket_dir: Path) -> None:
    """Let the sandbox's uid reach the evaluator's socket: group-owned, no access for others."""
    os.chown(socket_dir, -1, SANDBOX_GID)
    os.chmod(socket_dir, 0o710)
    for entry in os.scandir(socket_dir):
        if stat.S_ISSOCK(entry.stat(follow_symlinks=False).st_mode):
            os.chown(entry.path, -1, SANDBOX_GID)
            os.chmod(entry.path, 0o660)


def _tool(name: str) -> str:
    path = shutil.which(name)
    assert path is not None, "check unavailable() first"
    return path


def _data_fd(text: str) -> int:
    """A pipe's read end holding `text` (small enough for the pipe's buffer)."""
    read, write = os.pipe()
    try:
        os.write(write, text.encode())
    finally:
        os.close(write)
    return read
