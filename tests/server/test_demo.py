"""`make demo` is the quick start: `manieval demo` must evaluate the examples and fill the board."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.server.registry_fixture import require_tool

pytestmark = pytest.mark.sim


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
    first = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "submitted local:scripted" in first.stderr
    assert "succeeded" in first.stderr
    assert "maniskill-core leaderboard" in first.stdout
    assert first.stdout.count("baseline") == 2
    assert (tmp_path / "demo-password").stat().st_mode & 0o077 == 0
    # A participant's own policy: the registry it started, and the commands that reach it.
    assert f"registry: {registry}" in first.stderr
    assert "manieval push my-policy --challenge maniskill-core --wait" in first.stderr
    command[-1] = str(free_port())
    second = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "submitted" not in second.stderr  # finished work is reused
    assert second.stdout.count("baseline") == 2
