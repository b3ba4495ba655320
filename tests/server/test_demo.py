"""`make demo` is the quick start: `manieval demo` must evaluate the examples and fill the board."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.server.registry_fixture import require_tool

pytestmark = [pytest.mark.sim, pytest.mark.long]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# Both examples on the core track (six recorded videos each), the scripted one on the visual
# track (two), on a busy 2-core machine.
@pytest.mark.timeout(1500)
def test_demo_evaluates_the_examples_and_is_idempotent(tmp_path: Path) -> None:
    require_tool("docker-registry")
    registry = f"127.0.0.1:{free_port()}"
    env = {
        **os.environ,
        "MANIEVAL_DATA_DIR": str(tmp_path),
        "MANIEVAL_EMBEDDED_REGISTRY_ADDR": registry,
    }
    command = [
        sys.executable,
        "-m",
        "manieval",
        "demo",
        "--episodes",
        "1",
        "--exit-when-done",
        "--port",
        str(free_port()),
    ]
    first = subprocess.run(command, env=env, capture_output=True, text=True, timeout=1400)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "submitted local:scripted on maniskill-core" in first.stderr
    assert "submitted local:scripted on maniskill-visual" in first.stderr  # both tracks
    assert "succeeded" in first.stderr
    # Without a terminal, progress is a few lines (a quarter each), not one per episode.
    assert "None" not in first.stderr
    assert first.stderr.count(" episodes (") <= 3 * 3
    assert "maniskill-core leaderboard" in first.stdout
    assert "maniskill-visual leaderboard" in first.stdout
    assert first.stdout.count("baseline") == 3  # scripted and random; scripted on cameras
    assert (tmp_path / "demo-password").stat().st_mode & 0o077 == 0
    # A participant's own policy: the registry it started, and the commands that reach it.
    assert f"registry: {registry}" in first.stderr
    assert "manieval push my-policy --challenge maniskill-core --wait" in first.stderr
    command[-1] = str(free_port())
    second = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "submitted" not in second.stderr  # finished work is reused
    assert second.stdout.count("baseline") == 3


CRASHER = "import sys\nprint('cannot load weights.pt', file=sys.stderr)\nsys.exit(3)\n"
LAUNCHER = (
    "import sys, pathlib, evaluator.bundled\n"
    "evaluator.bundled.EXAMPLES_DIR = pathlib.Path(sys.argv[1])\n"
    "from manieval.cli import app\n"
    "app(sys.argv[2:], prog_name='manieval')\n"
)


def test_a_failed_demo_says_what_failed_and_what_to_do_next(tmp_path: Path) -> None:
    examples = tmp_path / "examples"
    for name in ("scripted", "random"):  # the demo's two examples, both broken
        (examples / name).mkdir(parents=True)
        (examples / name / "policy.py").write_text(CRASHER)
    env = {
        **os.environ,
        "MANIEVAL_DATA_DIR": str(tmp_path / "data"),
        "MANIEVAL_EMBEDDED_REGISTRY": "false",
        "MANIEVAL_EMBEDDED_ENGINE": "false",
    }
    port = str(free_port())
    args = ["demo", "--episodes", "1", "--exit-when-done", "--port", port]
    done = subprocess.run(
        [sys.executable, "-c", LAUNCHER, str(examples), *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 1, done.stderr[-3000:]
    assert "leaderboard" not in done.stdout  # no empty table
    err = done.stderr
    assert "none of the example policies succeeded" in err
    for track in ("scripted on maniskill-core", "random on maniskill-core"):
        assert f"(local:{track}) failed: " in err
    assert "(local:scripted on maniskill-visual) failed: " in err
    assert "exit code 3" in err  # the examples' own reasons
    assert "cannot load weights.pt" in err  # the end of their logs
    assert "manieval evaluate --policy examples/policies/random" in err
    assert "run manieval demo again" in err
    assert "serving" not in err
    assert (tmp_path / "data" / "demo.log").exists()
