"""Times and durations as the participant commands print them."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from datetime import UTC, datetime

import pytest

from manieval import render


@pytest.fixture
def zone() -> Iterator[None]:
    old = os.environ.get("TZ")
    os.environ["TZ"] = "ABC+3"  # POSIX: three hours west of UTC
    time.tzset()
    yield
    if old is None:
        del os.environ["TZ"]
    else:
        os.environ["TZ"] = old
    time.tzset()


@pytest.mark.parametrize(
    ("seconds", "shown"),
    [
        (0, "1 s"),
        (0.2, "1 s"),
        (59, "59 s"),
        (61, "2 min"),
        (3600, "1 h"),
        (3660, "1 h 1 min"),
        (86399, "24 h"),
        (3 * 86400 + 3600, "3 d 1 h"),
    ],
)
def test_durations_round_up_to_a_readable_unit(seconds: float, shown: str) -> None:
    assert render.duration(seconds) == shown


def test_times_are_shown_in_the_local_zone(zone: None) -> None:
    moment = datetime(2026, 11, 24, 10, 0, 30, tzinfo=UTC)
    assert render.local_time(moment) == "2026-11-24 07:00:30 ABC"
    assert render.local_time("2026-11-24T10:00:30+00:00") == "2026-11-24 07:00:30 ABC"
    assert render.local_time(None) == "-"


def test_terminal_escapes_in_a_log_are_defused_on_a_terminal_only() -> None:
    log = "ok\n\x1b[2Jcleared\tscreen\n"
    assert render.printable(log, terminal=True) == "ok\n\\x1b[2Jcleared\tscreen\n"
    assert render.printable(log, terminal=False) == log
