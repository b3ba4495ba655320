"""A real ManiEval server in a subprocess for the participant commands to talk to.

`start_server` runs `manieval serve` on a free port with embedded defaults in a fresh data
directory (SQLite, the inline queue, bundled `local:` policies), after loading tiny
challenges, and waits for /healthz. The commands are then driven through Typer's CliRunner
(or as subprocesses) with MANIEVAL_CONFIG_DIR in a temporary directory.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from typer.testing import CliRunner, Result

from manieval.cli import app
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.settings import Settings
from testkit.factories import PASSWORD, SUITE, embedded_database, gpu_suite
from testkit.waiting import process_tree_activity, until

REPO = Path(__file__).resolve().parents[2]
STARTUP_SECONDS = 90.0
# The server's example policies: the bundled ones, and one that crashes at once.
CRASHER = "import sys\nprint('loading weights... out of luck', file=sys.stderr)\nsys.exit(3)\n"
# Patches the directory of `local:` policies, then runs `manieval serve`.
LAUNCHER = (
    "import sys, pathlib, evaluator.bundled\n"
    "evaluator.bundled.EXAMPLES_DIR = pathlib.Path(sys.argv[1])\n"
    "from manieval.cli import app\n"
    "app(['serve', '--port', sys.argv[2]], prog_name='manieval')\n"
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class LiveServer:
    url: str
    data_dir: Path
    closed_port: int  # an allow-listed registry that nothing listens on
    log: Path


def ignore_sigint() -> None:
    """In a child before `exec`: SIGINT ignored, as `cmd &` in a non-interactive shell has it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def clean_environment() -> dict[str, str]:
    """This process's environment without any MANIEVAL_* setting of the developer's."""
    return {k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")}


def load_challenges(settings: Settings) -> None:
    """`server-tiny` and `server-long` (50 a day, 3 at once), `server-quota` (1 a day), and
    `server-gpu` (a GPU per policy, which this service has not)."""
    embedded_database(settings, quota_per_day=50, quota_concurrent=3)
    quota_suite = settings.data_dir / "server-quota.yaml"
    quota_suite.write_text(SUITE.read_text().replace("name: server-tiny", "name: server-quota"))
    from server.kit.db import make_engine, session_factory

    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        load_challenge(
            db,
            quota_suite,
            ChallengeOptions(quota_per_day=1, quota_concurrent=1),
            seed_secret=settings.secret("seed_secret"),
        )
        load_challenge(
            db,
            gpu_suite(settings.data_dir),
            ChallengeOptions(),
            seed_secret=settings.secret("seed_secret"),
        )


@contextmanager
def running_server(
    data_dir: Path,
    *,
    challenges: bool = True,
    extra: Mapping[str, str] | None = None,
    stop: signal.Signals = signal.SIGINT,
) -> Iterator[LiveServer]:
    """`manieval serve` in a subprocess until the block ends, then interrupted as by Ctrl-C
    (`stop`: or killed). A second server may run on the same `data_dir` afterwards."""
    data_dir.mkdir(parents=True, exist_ok=True)
    closed_port = free_port()
    env = (
        clean_environment()
        | {
            "MANIEVAL_DEV_MODE": "true",
            "MANIEVAL_DATA_DIR": str(data_dir),
            "MANIEVAL_ALLOW_LOCAL_POLICIES": "true",
            "MANIEVAL_COOKIE_SECURE": "false",
            "MANIEVAL_INLINE_WORKERS": "2",
            "MANIEVAL_LEADERBOARD_MAX_AGE": "0",
            "MANIEVAL_ALLOWED_REGISTRIES": f"127.0.0.1:{closed_port}",
            "MANIEVAL_REGISTRY_TIMEOUT": "3",
            "MANIEVAL_REGISTER_RATE": "1000/minute",
            "MANIEVAL_LOGIN_RATE": "1000/minute",
            "MANIEVAL_TOKEN_RATE": "1000/minute",
            "MANIEVAL_SUBMIT_RATE": "1000/minute",
            # The registry and Podman of the embedded default: tests/cli/test_push.py
            "MANIEVAL_EMBEDDED_REGISTRY": "false",
            "MANIEVAL_EMBEDDED_ENGINE": "false",
            "PYTHONUNBUFFERED": "1",
        }
        | dict(extra or {})
    )
    if challenges:
        load_challenges(Settings(dev_mode=True, data_dir=data_dir, cookie_secure=False))
    policies = data_dir / "policies"
    if not policies.exists():
        policies.mkdir()
        for name in ("scripted", "random"):
            (policies / name).symlink_to(REPO / "examples" / "policies" / name)
        (policies / "crasher").mkdir()
        (policies / "crasher" / "policy.py").write_text(CRASHER)
    port = free_port()
    log = data_dir / "server.log"
    with log.open("ab") as out:  # a second server on the same data appends
        process = subprocess.Popen(
            [sys.executable, "-c", LAUNCHER, str(policies), str(port)],
            env=env,
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    server = LiveServer(f"http://127.0.0.1:{port}", data_dir, closed_port, log)
    try:
        _wait_healthy(server, process)
        yield server
    finally:
        process.send_signal(stop)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _wait_healthy(server: LiveServer, process: subprocess.Popen[bytes]) -> None:
    """Until /healthz answers; the bound is on start-up making no progress (no log line, no CPU
    used by the server or what it runs: publishing the policy base takes a minute on a
    loaded machine), not on the time start-up takes."""

    def healthy() -> bool:
        if process.poll() is not None:
            pytest.fail(f"the server exited ({process.returncode}):\n{server.log.read_text()}")
        try:
            return httpx.get(f"{server.url}/healthz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    until(
        healthy,
        lambda: f"the server to answer /healthz:\n{server.log.read_text()}",
        timeout=STARTUP_SECONDS,
        every=0.1,
        progress=lambda: process_tree_activity(process.pid, server.log),
    )


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """One server per test module."""
    with running_server(tmp_path_factory.mktemp("server")) as server:
        yield server


# Driving the commands ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Participant:
    """One user's terminal: their own config directory, pointed at one server."""

    server: str
    config_dir: Path

    @property
    def env(self) -> dict[str, str | None]:
        return {
            "MANIEVAL_SERVER": self.server,
            "MANIEVAL_CONFIG_DIR": str(self.config_dir),
            "MANIEVAL_TOKEN": None,
            "COLUMNS": "200",
        }

    def run(
        self, *args: str, input: str | None = None, env: Mapping[str, str] | None = None
    ) -> Result:
        """`manieval ARGS` in this process, as CliRunner runs it."""
        return CliRunner().invoke(app, list(args), input=input, env=self.env | dict(env or {}))

    def spawn(self, *args: str, sigint_ignored: bool = False) -> subprocess.Popen[str]:
        """`manieval ARGS` as a real process (stdout and stderr piped, text); with
        `sigint_ignored`, started as a shell starts a background job."""
        env = clean_environment() | {k: v for k, v in self.env.items() if v is not None}
        return subprocess.Popen(
            [sys.executable, "-m", "manieval", *args],
            env=env | {"PYTHONUNBUFFERED": "1"},
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=ignore_sigint if sigint_ignored else None,
        )

    def register(self, username: str) -> None:
        r = self.run(
            "register",
            "-u",
            username,
            "--email",
            f"{username}@example.org",
            "--password-stdin",
            input=PASSWORD + "\n",
        )
        assert r.exit_code == 0, r.output

    def login(self, username: str) -> None:
        r = self.run("login", "-u", username, "--password-stdin", input=PASSWORD + "\n")
        assert r.exit_code == 0, r.output


def participant(server: LiveServer, tmp_path: Path, username: str) -> Participant:
    """A registered, logged-in participant."""
    someone = Participant(server.url, tmp_path / "config")
    someone.register(username)
    someone.login(username)
    return someone
