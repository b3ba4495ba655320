"""Local policies run in a bubblewrap sandbox: misbehaviour is contained and named.

The first tests check the command line and the limit logic as data. The rest run real policies
under real bwrap against the tiny suite; with CI=true a missing bwrap fails them.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from evaluator import sandbox, sources
from evaluator.endpoint import PolicyEndpoint
from evaluator.evaluation import evaluate
from evaluator.limits import Breach
from evaluator.results import EvaluationResult
from evaluator.sandbox import Usage, breached, minimal_cover
from evaluator.sandbox_command import (
    MIB,
    SANDBOX_UID,
    SandboxLimits,
    SandboxSpec,
    bwrap_command,
    staged_command,
)
from evaluator.sources import LocalDirectory
from tests.evaluator.conftest import tiny_plan

HEADER = """
import json, os, socket, subprocess, sys, time
import numpy as np
from manieval_sdk import Policy, serve

class Zero(Policy):
    def act(self, obs):
        return np.zeros(self.spec.action_shape, dtype=np.float32)
"""

# Small limits, so that reaching them is quick and cheap on a loaded machine.
SMALL = SandboxLimits(memory_mib=256, processes=48, scratch_mib=8)


def spec(**changes: object) -> SandboxSpec:
    fields: dict[str, object] = {
        "bwrap": "/usr/bin/bwrap",
        "python": "/venv/bin/python",
        "entrypoint": "policy.py",
        "workdir": Path("/home/alice/policy"),
        "socket_dir": Path("/tmp/manieval-x"),
        "runtime": (Path("/opt/python"), Path("/venv")),
        "system": (("/usr", None), ("/lib", "usr/lib")),
        "env": {"MANIEVAL_ENDPOINT": "unix:///tmp/manieval-x/policy.sock"},
        "limits": SandboxLimits(),
        "info_fd": 5,
        "passwd_fd": 6,
        "group_fd": 7,
    }
    fields.update(changes)
    return SandboxSpec(**fields)  # type: ignore[arg-type]


def options(args: list[str], flag: str) -> list[list[str]]:
    """The arguments that follow each occurrence of a bwrap option taking two."""
    return [args[i + 1 : i + 3] for i, arg in enumerate(args) if arg == flag]


def bwrap_part(args: list[str]) -> list[str]:
    return args[: args.index("--")]


def test_the_sandbox_shares_no_namespace_and_runs_as_an_unprivileged_uid():
    args = bwrap_part(bwrap_command(spec()))
    for flag in ("--unshare-all", "--unshare-user", "--disable-userns", "--die-with-parent"):
        assert flag in args
    assert "--share-net" not in args
    assert args[args.index("--uid") + 1] == str(SANDBOX_UID)


def test_the_environment_is_cleared_and_only_the_given_variables_are_set():
    args = bwrap_part(bwrap_command(spec(env={"A": "1", "MANIEVAL_ENDPOINT": "unix:///s"})))
    assert "--clearenv" in args
    assert options(args, "--setenv") == [["A", "1"], ["MANIEVAL_ENDPOINT", "unix:///s"]]


def test_every_host_path_is_bound_read_only_and_only_what_the_policy_needs():
    args = bwrap_part(bwrap_command(spec()))
    assert "--bind" not in args
    assert "--dev-bind" not in args
    bound = {dest for _, dest in options(args, "--ro-bind")}
    assert bound == {"/usr", "/opt/python", "/venv", "/home/alice/policy", "/tmp/manieval-x"}
    assert ["usr/lib", "/lib"] in options(args, "--symlink")
    assert ["/", "--chdir"] in options(args, "--remount-ro")  # the sandbox's own root, too


def test_scratch_space_is_a_size_limited_tmpfs_mounted_before_the_binds():
    args = bwrap_part(bwrap_command(spec(limits=SandboxLimits(scratch_mib=8))))
    tmp = args.index("/tmp")
    assert args[tmp - 3 : tmp] == ["--size", str(8 * MIB), "--tmpfs"]
    assert tmp < args.index("/tmp/manieval-x")
    assert "/dev/shm" in args


def test_limits_are_set_in_the_sandbox_before_the_policy_starts():
    command = bwrap_command(spec(limits=SandboxLimits(processes=10, open_files=20)))
    inner = command[command.index("--") + 1 :]
    assert inner[:3] == ["/venv/bin/python", "-I", "-S"]
    assert {"NPROC=10", "NOFILE=20", "CORE=0"} <= set(inner)
    assert inner[-2:] == ["/venv/bin/python", "policy.py"]


def test_as_root_the_sources_are_staged_and_bwrap_runs_as_the_sandbox_uid():
    staged = spec(stage=Path("/tmp/stage"))
    command = staged_command(staged, unshare="/usr/bin/unshare", setpriv="/usr/bin/setpriv")
    assert command[:4] == ["/usr/bin/unshare", "--mount", "--propagation", "private"]
    assert f"--reuid={SANDBOX_UID}" in command[6]  # the script that drops to the sandbox uid
    args = bwrap_part(command[command.index("/usr/bin/bwrap") :])
    assert ["/tmp/stage/0", "/opt/python"] in options(args, "--ro-bind")
    assert ["/tmp/stage/3", "/tmp/manieval-x"] in options(args, "--ro-bind")


def test_each_limit_is_named_when_reached():
    limits = SandboxLimits(memory_mib=100, processes=10, scratch_mib=8)
    fine = Usage(tasks=9, memory_bytes=99 * MIB, full_scratch=None)
    assert breached(fine, limits) is None
    kinds = [
        breached(Usage(tasks=10, memory_bytes=0, full_scratch=None), limits),
        breached(Usage(tasks=1, memory_bytes=100 * MIB, full_scratch=None), limits),
        breached(Usage(tasks=1, memory_bytes=0, full_scratch="/tmp"), limits),
    ]
    assert [b.kind if isinstance(b, Breach) else None for b in kinds] == [
        "process_limit",
        "memory_limit",
        "file_size_limit",
    ]


def test_runtime_paths_keep_only_the_outermost_directories():
    paths = [Path("/venv/lib/numpy"), Path("/venv"), Path("/usr/lib/python3"), Path("/src/sdk")]
    assert minimal_cover(paths, covered=[Path("/usr")]) == (Path("/venv"), Path("/src/sdk"))


# Real sandboxes from here on.


@pytest.fixture
def bwrap() -> None:
    problem = sandbox.unavailable()
    if problem is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"the sandbox tests need bubblewrap: {problem}")
    pytest.skip(problem)


def sandboxed(
    make_policy: Callable[[str], Path],
    body: str,
    *,
    limits: SandboxLimits = SMALL,
    episodes: int = 1,
) -> tuple[EvaluationResult, Path]:
    directory = make_policy(HEADER + body)
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=episodes)
    return evaluate(plan, LocalDirectory(directory, limits=limits)), directory


def probe_report(result: EvaluationResult) -> str:
    """What a probe policy found: it raises it as its error in the first episode."""
    episode = result.conditions[0].tasks[0].episodes[0]
    assert episode.failure == "policy_error", (episode, result.abort)
    assert episode.failure_reason is not None
    assert "probe:" in episode.failure_reason
    return episode.failure_reason.split("probe:", 1)[1]


def host_processes_in(directory: Path) -> list[int]:
    """Host processes whose working directory is `directory` (the policy's, and its forks')."""
    found = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                if os.readlink(f"/proc/{entry.name}/cwd") == str(directory):
                    found.append(int(entry.name))
            except OSError:
                continue
    return found


def assert_none_left(directory: Path) -> None:
    # A killed process may linger for a moment while the kernel tears its namespace down.
    deadline = time.monotonic() + 60
    while (left := host_processes_in(directory)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert left == [], f"processes of the policy outlived its evaluation: {left}"


def assert_stopped_by(result: EvaluationResult, kind: str, detail: str) -> None:
    assert result.status == "aborted"
    assert result.abort is not None
    assert result.abort.kind == kind, result.abort
    assert detail in result.abort.reason
    failures = [e.failure for e in result.conditions[0].tasks[0].episodes]
    assert kind in failures
    assert set(failures) <= {kind, "policy_error", "not_run"}


@pytest.fixture
def loopback_listener() -> Iterator[socket.socket]:
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    listener.setblocking(False)
    yield listener
    listener.close()


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_policy_cannot_reach_a_port_on_the_hosts_loopback(make_policy, loopback_listener):
    port = loopback_listener.getsockname()[1]
    result, _ = sandboxed(
        make_policy,
        f"""
class Probe(Zero):
    def act(self, obs):
        try:
            socket.create_connection(("127.0.0.1", {port}), timeout=5).close()
            found = "connected"
        except OSError as exc:
            found = type(exc).__name__
        raise RuntimeError("probe:" + found)
serve(Probe())
""",
    )
    assert probe_report(result) in {"ConnectionRefusedError", "OSError"}  # its own empty loopback
    with pytest.raises(BlockingIOError):
        loopback_listener.accept()


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_policy_cannot_read_the_evaluators_environment_or_any_other_process(
    make_policy, monkeypatch
):
    monkeypatch.setenv("MANIEVAL_SEED_SECRET", "sekrit-seed-material")
    result, _ = sandboxed(
        make_policy,
        f"""
class Probe(Zero):
    def act(self, obs):
        seen, pids = [], []
        for name in ["{os.getpid()}", str(os.getppid()), *os.listdir("/proc")]:
            try:
                environ = open(f"/proc/{{name}}/environ", "rb").read()
            except OSError:
                continue
            pids.append(name)
            seen.append(b"sekrit" in environ or b"MANIEVAL_SEED" in environ)
        others = [p for p in os.listdir("/proc") if p.isdigit() and int(p) > 2]
        raise RuntimeError(f"probe:secret={{any(seen)}} read={{len(pids)}} others={{others}}")
serve(Probe())
""",
    )
    report = probe_report(result)
    assert "secret=False" in report
    assert "read=0" not in report  # it did read environments: its own and its sandbox's init
    assert "others=[]" in report  # no process of the host, not even the evaluator, is visible


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_policy_sees_no_host_secrets_and_can_write_only_its_scratch_space(make_policy):
    result, directory = sandboxed(
        make_policy,
        """
def attempt(action):
    try:
        action()
        return "ok"
    except OSError as exc:
        return type(exc).__name__

class Probe(Zero):
    def act(self, obs):
        found = {
            "shadow": attempt(lambda: open("/etc/shadow").read()),
            "etc": sorted(os.listdir("/etc")),
            "root": attempt(lambda: open("/escape", "w").write("x")),
            "policy": attempt(lambda: open("mine", "w").write("x")),
            "dev": attempt(lambda: open("/dev/escape", "w").write("x")),
            "tmp": attempt(lambda: open("/tmp/scratch", "w").write("x")),
        }
        raise RuntimeError("probe:" + json.dumps(found))
serve(Probe())
""",
    )
    found = json.loads(probe_report(result))
    assert found["shadow"] == "FileNotFoundError"
    assert set(found["etc"]) <= {
        *("alternatives", "group", "ld.so.cache", "ld.so.conf", "ld.so.conf.d", "localtime"),
        "passwd",
    }
    assert [found[place] for place in ("root", "policy", "dev")] == ["OSError"] * 3  # read-only
    assert found["tmp"] == "ok"
    assert not (directory / "mine").exists()


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_fork_bomb_is_capped_and_stopped_as_process_limit(make_policy):
    result, directory = sandboxed(
        make_policy,
        """
class Bomb(Zero):
    def act(self, obs):
        while True:
            try:
                os.fork()
            except OSError:
                time.sleep(0.05)
serve(Bomb())
""",
    )
    assert_stopped_by(result, "process_limit", f"at its limit of {SMALL.processes} processes")
    assert_none_left(directory)


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_memory_hog_is_stopped_as_memory_limit(make_policy):
    result, directory = sandboxed(
        make_policy,
        """
class Hog(Zero):
    hoard = []
    def act(self, obs):
        try:
            while True:
                self.hoard.append(np.ones(8 << 20, dtype=np.uint8))
        except MemoryError:
            time.sleep(3600)  # and holds on to it, as a leak does
serve(Hog())
""",
    )
    assert_stopped_by(result, "memory_limit", f"at its memory limit of {SMALL.memory_mib} MiB")
    assert_none_left(directory)


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_disk_filler_is_stopped_as_file_size_limit(make_policy):
    result, directory = sandboxed(
        make_policy,
        """
class Filler(Zero):
    def act(self, obs):
        try:
            with open("/tmp/fill", "wb") as f:
                while True:
                    f.write(b"x" * (1 << 20))
        except OSError:
            time.sleep(3600)
serve(Filler())
""",
    )
    assert_stopped_by(result, "file_size_limit", f"with its /tmp full ({SMALL.scratch_mib} MiB)")
    assert_none_left(directory)


@pytest.mark.sim
@pytest.mark.usefixtures("bwrap")
def test_a_setsid_grandchild_dies_with_a_completed_run(make_policy):
    result, directory = sandboxed(
        make_policy,
        """
class Escape(Zero):
    def setup(self, spec):
        super().setup(spec)
        subprocess.Popen(
            [sys.executable, "-c", "import os, time; os.fork(); time.sleep(3600)"],
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
serve(Escape())
""",
    )
    assert result.status == "completed"
    assert_none_left(directory)


@pytest.mark.usefixtures("bwrap")
def test_the_sdk_starts_in_the_sandbox_as_an_unprivileged_user(make_policy):
    directory = make_policy(HEADER + "print('uid', os.getuid(), flush=True)\nserve(Zero())\n")
    endpoint = PolicyEndpoint()
    process = LocalDirectory(directory).launch(
        endpoint=endpoint.address, socket_dir=endpoint.socket_dir
    )
    try:
        endpoint.accept(timeout=120, alive=process.alive)
        assert endpoint.hello(timeout=120)["type"] == "ready"
    finally:
        endpoint.close()
        process.stop()
    assert f"uid {SANDBOX_UID}" in process.log_tail()


def test_without_bubblewrap_the_policy_runs_unconfined_after_one_warning(
    make_policy, monkeypatch, caplog
):
    monkeypatch.setenv("PATH", "/nonexistent")
    sources.warn_unconfined.cache_clear()
    directory = make_policy(HEADER + "print('uid', os.getuid(), flush=True)\nserve(Zero())\n")
    with caplog.at_level(logging.WARNING, logger="evaluator.sources"):
        source = LocalDirectory(directory)
        LocalDirectory(directory)
    assert [r.getMessage() for r in caplog.records] == [
        "bubblewrap (bwrap) is not installed: the policy runs unconfined, as your user, with "
        "your files and network"
    ]
    endpoint = PolicyEndpoint()
    process = source.launch(endpoint=endpoint.address, socket_dir=endpoint.socket_dir)
    try:
        endpoint.accept(timeout=120, alive=process.alive)
        assert endpoint.hello(timeout=120)["type"] == "ready"
    finally:
        endpoint.close()
        process.stop()
    assert f"uid {os.getuid()}" in process.log_tail()
