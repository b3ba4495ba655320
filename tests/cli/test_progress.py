"""The progress displays of `submit --wait`, `demo` and `evaluate` without a terminal: a few
plain lines with the time left, never one line per episode."""

from __future__ import annotations

from typing import Any

from rich.console import Console

from manieval import render
from manieval.evaluate import RunLines
from manieval.follow import LineView, Pace


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _running(done: int | None, total: int = 72, **progress: Any) -> dict[str, Any]:
    return {
        "id": 7,
        "state": "running",
        "reason": "",
        "progress": {"done": done, "total": total, **progress},
        "queue": None,
    }


def test_a_submission_without_a_terminal_gets_a_line_per_quarter_with_the_time_left() -> None:
    clock = Clock()
    console = Console(record=True, width=200)
    view = LineView(console, names={7: "local:scripted"}, clock=clock)
    view.show(_running(0))  # the worker's first report names no task yet
    for done in range(1, 73):
        clock.now += 2.0
        view.show(_running(done, task="PickCube-v1", condition="nominal"))
    view.show({**_running(72), "state": "succeeded", "reason": "evaluated 72 episodes"})
    lines = console.export_text().splitlines()
    assert lines[0] == "submission 7 (local:scripted): running"
    progress = [line for line in lines if "episodes (" in line]
    assert progress == [
        "submission 7 (local:scripted): 18/72 episodes (PickCube-v1, nominal), about 2 min left",
        "submission 7 (local:scripted): 36/72 episodes (PickCube-v1, nominal), about 2 min left",
        "submission 7 (local:scripted): 54/72 episodes (PickCube-v1, nominal), about 36 s left",
    ]
    assert lines[-1] == "submission 7 (local:scripted): succeeded (evaluated 72 episodes)"
    assert "None" not in console.export_text()
    assert len(lines) == 5


def test_progress_text_never_shows_a_missing_task() -> None:
    assert render.progress_text({"done": 0, "total": 72}) == "0/72 episodes"
    assert render.progress_text({"done": None, "total": 72, "task": None}) == "0/72 episodes"
    assert render.progress_text({"done": 3, "total": 8, "task": "PickCube-v1"}) == (
        "3/8 episodes (PickCube-v1)"
    )
    assert render.progress_text(None) == ""


def test_the_time_left_is_estimated_from_the_pace_seen_since_following_began() -> None:
    clock = Clock()
    pace = Pace(clock)
    assert pace.left(30, 72) == ""  # first sight: no pace yet (30 were done before)
    clock.now += 10
    assert pace.left(40, 72) == "about 32 s left"
    assert render.time_left(5.0, 0, 10) == ""
    assert render.time_left(5.0, 10, 10) == ""


def test_evaluate_without_a_terminal_says_each_finished_task_with_the_time_left() -> None:
    clock = Clock()
    console = Console(record=True, width=200)
    runs = [("PickCube-v1", "nominal", 2), ("PushCube-v1", "nominal", 2)]
    with RunLines(console, runs, clock=clock) as shown:
        for index, success in [(0, True), (0, False), (1, True), (1, True)]:
            clock.now += 3.0
            shown.episode(index, success)
    assert console.export_text().splitlines() == [
        "evaluating 4 episodes: 2 tasks under 1 conditions",
        "PickCube-v1 (nominal): 1/2 succeeded; 2/4 episodes done, about 6 s left",
        "PushCube-v1 (nominal): 2/2 succeeded; 4/4 episodes done",
    ]
