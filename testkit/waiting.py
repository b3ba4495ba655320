"""Waiting in tests: on the event itself, polled, within a bound generous enough for a busy
machine. A bound is a limit on giving up, never a measurement: a test that waits here passes as
soon as the event happens, and fails with what it waited for and the last thing it saw."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def until(
    check: Callable[[], T],
    what: str | Callable[[], str],
    *,
    timeout: float = 30.0,
    every: float = 0.05,
) -> T:
    """Call `check` until it returns something true, and return that.

    `check` may itself fail the test (a process that exited, a state that can no longer
    change); the wait fails naming `what` once `timeout` seconds pass without it (a callable
    `what` is asked then, to describe the state the wait gave up in: a process's output)."""
    deadline = time.monotonic() + timeout
    while not (value := check()):
        if time.monotonic() > deadline:
            said = what() if callable(what) else what
            raise AssertionError(f"gave up after {timeout:g} s waiting for {said}")
        time.sleep(every)
    return value


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
