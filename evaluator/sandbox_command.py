"""What bubblewrap (`bwrap`) is told when it confines a local policy: plain data, built without I/O.

The policy sees a read-only view of only what it needs (the system's shared libraries, the Python
installation and virtualenv, the SDK, its own directory and the evaluator's socket directory),
size-limited scratch space at `/tmp` and `/dev/shm`, a `/proc` of its own, no network, no other
process and a minimal environment. Every descendant lives in the sandbox's PID namespace, which
the kernel empties when the sandbox ends. The kernel's limits cap processes, memory per process,
file size and open files, set inside the sandbox before the policy starts.

As root, the policy runs as uid 65532 rather than as root mapped into a user namespace: root is
exempt from RLIMIT_NPROC, and root-owned files would be its own. bubblewrap then starts as that
user, after a private mount namespace has made the runtime's directories (which may sit below
root-only ones such as /root) reachable at a staging directory.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

SANDBOX_UID = 65532
SANDBOX_GID = 65532
MIB = 1 << 20
SCRATCH_DIRS = ("/tmp", "/dev/shm")
# The dynamic loader's cache and configuration, alternatives symlinks, the time zone: no secrets.
SYSTEM_FILES = (
    "/etc/ld.so.cache",
    "/etc/ld.so.conf",
    "/etc/ld.so.conf.d",
    "/etc/alternatives",
    "/etc/localtime",
)
PASSWD = f"root:x:0:0::/:/usr/sbin/nologin\npolicy:x:{SANDBOX_UID}:{SANDBOX_GID}::/tmp:/bin/sh\n"
GROUP = f"root:x:0:\npolicy:x:{SANDBOX_GID}:\n"
# What bubblewrap's own processes see; the policy gets only what `--setenv` gives it.
OUTER_ENV = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin"}

# Inside the sandbox, before the policy starts: set the kernel's hard limits, then exec it.
BOOTSTRAP = """\
import os, resource, sys
split = sys.argv.index("--")
for spec in sys.argv[1:split]:
    name, _, value = spec.partition("=")
    kind = getattr(resource, "RLIMIT_" + name)
    hard = resource.getrlimit(kind)[1]
    limit = int(value) if hard == resource.RLIM_INFINITY else min(int(value), hard)
    resource.setrlimit(kind, (limit, limit))
os.execv(sys.argv[split + 1], sys.argv[split + 1 :])
"""

# As root: in a private mount namespace, bind each source below the staging directory (reachable
# by the sandbox's uid whatever the modes of the source's parents), then become that uid and
# exec bubblewrap. Arguments: staging dir, setpriv, sources..., --, bwrap command.
STAGE_SCRIPT = f"""\
set -eu
stage=$1
setpriv=$2
shift 2
mount -t tmpfs -o size=1m,mode=0755 manieval-stage "$stage"
i=0
while [ "$1" != -- ]; do
  mkdir "$stage/$i"
  mount --bind "$1" "$stage/$i"
  i=$((i + 1))
  shift
done
shift
exec "$setpriv" --reuid={SANDBOX_UID} --regid={SANDBOX_GID} --clear-groups --inh-caps=-all \\
  --no-new-privs -- "$@"
"""


@dataclass(frozen=True)
class SandboxLimits:
    """What one sandboxed policy may use (the docker executor's defaults)."""

    memory_mib: int = 2048  # proportional resident memory of all its processes together
    processes: int = 256  # processes and threads
    scratch_mib: int = 64  # each of /tmp and /dev/shm, and the largest file it may write
    open_files: int = 1024

    def rlimits(self) -> dict[str, int]:
        """The kernel's hard limits, set inside the sandbox before the policy starts."""
        return {
            "NPROC": self.processes,
            # Per process, a backstop: the watcher stops the sandbox at memory_mib in total; this
            # keeps one runaway allocation from outrunning it.
            "DATA": 2 * self.memory_mib * MIB,
            "FSIZE": self.scratch_mib * MIB,
            "NOFILE": self.open_files,
            "CORE": 0,
        }


@dataclass(frozen=True)
class SandboxSpec:
    """Everything a sandbox's command line is made of: plain data, so it is built without I/O."""

    bwrap: str
    python: str
    entrypoint: str
    workdir: Path  # the policy directory: read-only, and the working directory
    socket_dir: Path
    runtime: tuple[Path, ...]  # read-only: the Python installation, virtualenv, SDK
    system: tuple[tuple[str, str | None], ...]  # (path, symlink target or None for a directory)
    env: Mapping[str, str]
    limits: SandboxLimits
    info_fd: int
    passwd_fd: int
    group_fd: int
    stage: Path | None = None  # as root: where the sources are staged (see STAGE_SCRIPT)

    def sources(self) -> list[Path]:
        """The host directories the sandbox sees read-only, beyond the system's."""
        return [*self.runtime, self.workdir, self.socket_dir]


def bwrap_command(spec: SandboxSpec) -> list[str]:
    """The bubblewrap command line that runs `python entrypoint` confined."""
    args = [spec.bwrap, "--unshare-all", "--unshare-user", "--disable-userns"]
    args += ["--die-with-parent", "--new-session", "--hostname", "policy"]
    args += ["--uid", str(SANDBOX_UID), "--gid", str(SANDBOX_GID)]
    args += ["--info-fd", str(spec.info_fd), "--clearenv"]
    for name, value in spec.env.items():
        args += ["--setenv", name, value]
    for path, target in spec.system:
        args += ["--symlink", target, path] if target is not None else ["--ro-bind", path, path]
    for path in SYSTEM_FILES:
        args += ["--ro-bind-try", path, path]
    args += ["--ro-bind-data", str(spec.passwd_fd), "/etc/passwd"]
    args += ["--ro-bind-data", str(spec.group_fd), "/etc/group"]
    args += ["--dev", "/dev", "--proc", "/proc"]
    for path in SCRATCH_DIRS:  # before the binds: the policy or socket directory may be in /tmp
        args += ["--size", str(spec.limits.scratch_mib * MIB), "--tmpfs", path]
    for index, source in enumerate(spec.sources()):
        shown = source if spec.stage is None else spec.stage / str(index)
        args += ["--ro-bind", str(shown), str(source)]
    args += ["--remount-ro", "/dev", "--remount-ro", "/", "--chdir", str(spec.workdir)]
    limits = [f"{name}={value}" for name, value in spec.limits.rlimits().items()]
    bootstrap = [spec.python, "-I", "-S", "-c", BOOTSTRAP, *limits, "--"]
    return [*args, "--", *bootstrap, spec.python, spec.entrypoint]


def staged_command(spec: SandboxSpec, *, unshare: str, setpriv: str) -> list[str]:
    """As root: stage the sources in a private mount namespace, then run bwrap as the sandbox's
    uid (see STAGE_SCRIPT)."""
    assert spec.stage is not None
    sources = [str(source) for source in spec.sources()]
    script = ["/bin/sh", "-c", STAGE_SCRIPT, "manieval-stage", str(spec.stage), setpriv]
    unshared = [unshare, "--mount", "--propagation", "private"]
    return [*unshared, *script, *sources, "--", *bwrap_command(spec)]
