"""The suite's waits (testkit/waiting.py): a wait on progress outlasts its bound while progress
goes on, and gives up once it stops or the cap is reached; the activity of a process tree."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from testkit import waiting
from testkit.waiting import process_tree_activity, until


def test_a_wait_on_progress_goes_on_past_its_bound_while_there_is_progress() -> None:
    calls = itertools.count()
    steps = itertools.count()
    # 40 checks of 10 ms each outlast the 20 ms bound whatever the machine: only progress
    # (a new value at every look) keeps the wait going.
    assert until(
        lambda: next(calls) >= 40, "40 calls", timeout=0.02, every=0.01, progress=steps.__next__
    )


def test_a_wait_on_progress_gives_up_once_progress_stops() -> None:
    with pytest.raises(AssertionError, match="without progress waiting for nothing"):
        until(lambda: False, "nothing", timeout=0.05, every=0.01, progress=lambda: 1)


def test_a_wait_whose_progress_never_stops_ends_at_the_cap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(waiting, "PROGRESS_CAP_S", 0.1)
    steps = itertools.count()
    with pytest.raises(AssertionError, match="waiting for a spinner"):
        until(lambda: False, "a spinner", timeout=0.02, every=0.01, progress=steps.__next__)


def test_the_activity_of_a_tree_counts_a_grandchilds_cpu_and_the_logs(tmp_path: Path) -> None:
    log = tmp_path / "log"
    spin = "while True: pass"
    # A shell whose child spins: the shell itself uses no CPU while it waits.
    shell = subprocess.Popen(
        ["/bin/sh", "-c", f'"{sys.executable}" -c "{spin}" & wait'], start_new_session=True
    )
    try:
        ticks, size = process_tree_activity(shell.pid, log)
        assert size == -1  # no log yet
        until(
            lambda: process_tree_activity(shell.pid)[0] > ticks,
            "the spinning grandchild's CPU time to count",
            timeout=60,
        )
        log.write_text("started\n")
        assert process_tree_activity(shell.pid, log)[1] == len("started\n")
    finally:
        os.killpg(shell.pid, signal.SIGKILL)  # the shell and its child: the group it leads
        shell.wait(timeout=60)
