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


def _queued(queue: dict[str, object] | None) -> dict[str, object]:
    return {
        "id": 7,
        "attempt": 1,
        "challenge": "maniskill-core",
        "phase": "dev",
        "state": "queued",
        "reason": "waiting for a worker",
        "progress": None,
        "queue": queue,
        "image": "127.0.0.1:5000/alice/p:v1",
        "pinned_image": "127.0.0.1:5000/alice/p@sha256:" + "0" * 64,
        "public": True,
        "created_at": "2026-01-01T12:00:00+00:00",
        "finished_at": None,
        "score": None,
        "description": "",
    }


def test_a_queued_submission_shows_its_place_in_status_and_while_waiting() -> None:
    from rich.console import Console

    from manieval.follow import LineView

    place = {
        "position": 3,
        "ahead": 2,
        "expected_start_s": 240,
        "text": "3rd in the queue, about 4 min",
    }
    console = Console(record=True, width=200)
    console.print(render.submission_summary(_queued(place)))
    assert "queue       3rd in the queue, about 4 min" in console.export_text()

    lines = Console(record=True, width=200)
    view = LineView(lines)
    view.show(_queued(place))
    view.show(_queued(place))  # unchanged: said once
    view.show(_queued({**place, "position": 2, "text": "2nd in the queue, about 2 min"}))
    text = lines.export_text()
    assert text.count("3rd in the queue, about 4 min") == 1
    assert "submission 7: 2nd in the queue, about 2 min" in text
    assert render.queue_text(None) == ""


NAMES = ("alice", "bob", "carol", "random")


def test_the_terminal_board_keeps_the_suites_order_and_marks_tie_groups() -> None:
    from rich.console import Console

    def row(
        rank: int | None, user: str, group: int | None, tied: bool = False
    ) -> dict[str, object]:
        return {
            "rank": rank,
            "username": user,
            "submission_id": 1,
            "score": 0.5,
            "tied": tied,
            "tie_group": group,
            "tasks": {t: {"success_rate": 0.5} for t in ("StackCube-v1", "PickCube-v1")},
            "conditions": {"obs_noise": 0.4, "nominal": 0.5},
        }

    board = {
        "challenge": "core",
        "phase": "dev",
        "page": 1,
        "per_page": 50,
        "total": 4,
        "tasks": ["StackCube-v1", "PickCube-v1"],  # the suite's order, not the alphabet's
        "conditions": ["nominal", "obs_noise"],
        "items": [
            row(1, "alice", 1),
            row(2, "bob", 1, tied=True),
            row(3, "carol", 2),
            row(None, "random", None),
        ],
    }
    console = Console(width=200, record=True)
    console.print(render.leaderboard_table(board))
    text = console.export_text()
    header = next(line for line in text.splitlines() if "rank" in line)
    assert header.index("StackCube-v1") < header.index("PickCube-v1")
    assert header.index("nominal") < header.index("obs_noise")
    assert "=2" in text
    assert "baseline" in text
    line = {u: next(x for x in text.splitlines() if f" {u} " in x) for u in NAMES}
    assert [[c.strip() for c in line[u].split("│")][1:3] for u in NAMES] == [
        ["1", "G1"],
        ["=2", "G1"],
        ["3", "G2"],
        ["baseline", ""],
    ]


def test_a_team_row_names_the_team_beside_its_display_name_and_who_submitted() -> None:
    from rich.console import Console

    row = {
        "rank": 1,
        "username": "ada",
        "team": "grasp-lab",
        "team_display_name": "alice",  # anyone may pick a display name: the name tells
        "submission_id": 1,
        "score": 0.5,
        "tasks": {"PickCube-v1": {"success_rate": 0.5}},
        "conditions": {"nominal": 0.5},
    }
    board = {"tasks": ["PickCube-v1"], "conditions": ["nominal"], "items": [row], "total": 1}
    board |= {"challenge": "core", "phase": "dev", "page": 1, "per_page": 50}
    console = Console(width=200, record=True)
    console.print(render.leaderboard_table(board))
    assert "alice (grasp-lab) by ada" in console.export_text()


def _task(condition: str, ran: int, planned: int, successes: int) -> dict[str, object]:
    complete = ran == planned
    return {
        "condition": condition,
        "env_id": "PickCube-v1",
        "episodes": planned,
        "episodes_ran": ran,
        "successes": successes,
        "success_rate": successes / planned if complete else None,
        "ci_low": 0.1 if complete else None,
        "ci_high": 0.9 if complete else None,
        "mean_steps": 10.0 if ran else None,
    }


def test_a_submission_that_ended_part_way_shows_what_ran_and_no_rate() -> None:
    from rich.console import Console

    base = {"id": 7, "challenge": "c", "phase": "dev", "score": None}
    tasks = [_task("nominal", 4, 4, 2), _task("noise", 1, 4, 1)]
    part = {**base, "tasks": tasks, "conditions": {"nominal": 0.5}}  # as the API gives them
    console = Console(record=True, width=200)
    shown = render.results(part)
    assert shown is not None
    console.print(shown)
    text = console.export_text()
    assert "0.50 [0.10, 0.90] 2/4" in text  # a task whose every episode ran
    assert "1 of 4 ran, 1 succeeded" in text
    assert "0.500" in text  # the mean of the condition that ran to its end, and no other
    none = {**base, "tasks": [_task("nominal", 0, 4, 0), _task("noise", 0, 4, 0)]}
    assert str(render.results(none)) == "no episodes ran"
    assert render.results({**base, "tasks": []}) is None
