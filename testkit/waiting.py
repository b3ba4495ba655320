"""Waiting in tests: on the event itself, polled, within a bound generous enough for a busy
machine. A bound is a limit on giving up, never a measurement: a test that waits here passes as
soon as the event happens, and fails with what it waited for and the last thing it saw."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

PROGRESS_CAP_S = 900.0
"""The longest a wait on progress goes on while progress never stops (a process that spins)."""


def until(
    check: Callable[[], T],
    what: str | Callable[[], str],
    *,
    timeout: float = 30.0,
    every: float = 0.05,
    progress: Callable[[], object] | None = None,
) -> T:
    """Call `check` until it returns something true, and return that.

    `check` may itself fail the test (a process that exited, a state that can no longer
    change); the wait fails naming `what` once `timeout` seconds pass without it (a callable
    `what` is asked then, to describe the state the wait gave up in: a process's output).

    With `progress`, `timeout` bounds the time without progress instead: the wait goes on while
    `progress()` keeps returning something new (a log that grows, the CPU time a process tree
    uses: `process_tree_activity`), for `PROGRESS_CAP_S` at most. A slow machine then makes a
    wait longer, never a failure; a process that stopped moving still fails in `timeout`."""
    started = time.monotonic()
    deadline = started + timeout
    seen = progress() if progress is not None else None
    while not (value := check()):
        now = time.monotonic()
        if progress is not None and (latest := progress()) != seen:
            seen, deadline = latest, min(now + timeout, started + PROGRESS_CAP_S)
        if now > deadline:
            said = what() if callable(what) else what
            quiet = " without progress" if progress is not None else ""
            raise AssertionError(f"gave up after {timeout:g} s{quiet} waiting for {said}")
        time.sleep(every)
    return value


def process_tree_activity(pid: int, *files: Path) -> tuple[int, ...]:
    """What changes while process `pid` works: the CPU time (in clock ticks) it, its live
    descendants and the children they waited for have used, and the size of each of `files`
    (its logs). Linux only (/proc)."""
    ticks, pending, seen = 0, [pid], set()
    while pending:
        current = pending.pop()
        if current in seen:
            continue
        seen.add(current)
        try:
            fields = Path(f"/proc/{current}/stat").read_text().rsplit(")", 1)[1].split()
            ticks += sum(int(value) for value in fields[11:15])  # utime stime cutime cstime
            for task in Path(f"/proc/{current}/task").iterdir():
                pending += [int(child) for child in (task / "children").read_text().split()]
        except (OSError, IndexError, ValueError):  # it ended while read
            continue
    sizes = [path.stat().st_size if path.exists() else -1 for path in files]
    return (ticks, *sizes)


def poll(
    fetch: Callable[[], T],
    done: Callable[[T], object],
    what: str,
    *,
    timeout: float = 30.0,
    every: float = 0.2,
) -> T:
    """Call `fetch` until `done` holds for what it returned, and return that; on giving up, the
    failure shows the last value fetched (a submission's body, the containers left)."""
    deadline = time.monotonic() + timeout
    while not done(value := fetch()):
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up after {timeout:g} s waiting for {what}; last: {value!r}")
        time.sleep(every)
    return value
