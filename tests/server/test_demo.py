"""`make demo` is the quick start. A demo whose examples fail says what failed and what to do
next. The demo that succeeds (started, stopped mid-evaluation, started again to the end, and
again) is in `tests/server/test_serve_stop.py`, with the other tests that stop the service."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.sim


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
