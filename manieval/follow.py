"""Following submissions until they end: on a terminal a live display (episodes done of the
total, the task being run, the time left at the pace so far), elsewhere a few plain lines.

`manieval submit/push/status --wait` follow one submission; `manieval demo` follows its
example policies together.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from types import TracebackType
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
)
from rich.text import Text

from manieval import render
from manieval.client import ApiError, Client, ClientError, Unreachable

JSON = dict[str, Any]
FINAL_STATES = frozenset({"succeeded", "failed", "error", "cancelled", "timed_out"})
POLL_SECONDS = 1.0
MAX_MISSES = 5  # polls in a row that may fail (server restarting, a network blip)
LINE_STEPS = 4  # without a terminal: a progress line at each quarter of the episodes


def follow(client: Client, submission_id: int, *, interval: float = POLL_SECONDS) -> JSON:
    """Poll until the submission ends and return its final detail (Ctrl-C propagates)."""
    return follow_all(client, [submission_id], interval=interval)[0]


def follow_all(
    client: Client,
    ids: Sequence[int],
    *,
    names: Mapping[int, str] | None = None,
    interval: float = POLL_SECONDS,
    console: Console | None = None,
) -> list[JSON]:
    """Poll until every submission ends; their final details, in the order of `ids`.

    `names` (e.g. the image) are shown after the submission's number.
    """
    console = console or render.stderr()
    view: View = (
        LiveView(console, names=names) if console.is_terminal else LineView(console, names=names)
    )
    latest: dict[int, JSON] = {}
    misses = 0
    with view:
        while True:
            try:
                for sid in ids:
                    if sid not in latest or latest[sid]["state"] not in FINAL_STATES:
                        latest[sid] = client.submission(sid)
                        view.show(latest[sid])
            except ClientError as exc:
                if not _transient(exc) or misses >= MAX_MISSES:
                    raise
                misses += 1
                view.note(f"no answer from the server ({exc}); trying again")
                time.sleep(interval * 2**misses)
                continue
            misses = 0
            if all(latest[sid]["state"] in FINAL_STATES for sid in ids):
                return [latest[sid] for sid in ids]
            time.sleep(interval)


def _transient(exc: ClientError) -> bool:
    return isinstance(exc, Unreachable) or (
        isinstance(exc, ApiError) and (exc.status >= 500 or exc.status == 429)
    )


def state_line(s: JSON, name: str | None = None) -> Text:
    """``submission 7: running`` with the reason when it has ended."""
    label = f"submission {s['id']}" + (f" ({name})" if name else "")
    line = Text(f"{label}: ") + render.state(s["state"])
    if s["state"] in FINAL_STATES and s.get("reason"):
        line.append(f" ({s['reason']})")
    return line


class Pace:
    """The time left at the pace seen since the submission was first seen running."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.first: tuple[float, int] | None = None

    def left(self, done: int, total: int) -> str:
        now = self.clock()
        if self.first is None:
            self.first = (now, done)
            return ""
        started, done_then = self.first
        return render.time_left(now - started, done - done_then, total - done_then)


class View:
    """Prints each change of state; subclasses add the progress."""

    def __init__(self, console: Console, *, names: Mapping[int, str] | None = None) -> None:
        self.console = console
        self.names = dict(names or {})
        self.last_state: dict[int, str] = {}

    def __enter__(self) -> View:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        return None

    def label(self, s: JSON) -> str:
        name = self.names.get(s["id"])
        return f"submission {s['id']}" + (f" ({name})" if name else "")

    def show(self, s: JSON) -> None:
        if s["state"] != self.last_state.get(s["id"]):
            self.last_state[s["id"]] = s["state"]
            self.print(state_line(s, self.names.get(s["id"])))

    def print(self, text: Text) -> None:
        self.console.print(text)

    def note(self, text: str) -> None:
        self.print(Text(text, style="yellow"))


class LineView(View):
    """For logs and pipes: a line per change of state or place in the queue, and one at each
    quarter of the episodes, with the time left."""

    def __init__(
        self,
        console: Console,
        *,
        names: Mapping[int, str] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(console, names=names)
        self.clock = clock
        self.queue_text: dict[int, str] = {}
        self.step: dict[int, int] = {}
        self.paces: dict[int, Pace] = {}

    def show(self, s: JSON) -> None:
        super().show(s)
        sid = s["id"]
        if s["state"] == "queued":
            place = render.queue_text(s.get("queue"))
            if place and place != self.queue_text.get(sid):
                self.queue_text[sid] = place
                self.print(Text(f"{self.label(s)}: {place}"))
            return
        progress = s.get("progress") or {}
        total, done = progress.get("total") or 0, progress.get("done") or 0
        if s["state"] != "running" or not total:
            return
        left = self.paces.setdefault(sid, Pace(self.clock)).left(done, total)
        step = done * LINE_STEPS // total
        if done and step > self.step.get(sid, 0) and done < total:
            self.step[sid] = step
            line = f"{self.label(s)}: {render.progress_text(progress)}"
            self.print(Text(line + (f", {left}" if left else "")))


class LiveView(View):
    """For a terminal: state changes printed above one live bar per submission."""

    def __init__(self, console: Console, *, names: Mapping[int, str] | None = None) -> None:
        super().__init__(console, names=names)
        self.progress = Progress(
            SpinnerColumn(),
            TextColumn("{task.description}", markup=False),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("episodes"),
            TimeElapsedColumn(),
            TextColumn("{task.fields[left]}", markup=False),
            console=console,
            transient=True,
        )
        self.tasks: dict[int, TaskID] = {}
        self.paces: dict[int, Pace] = {}

    def __enter__(self) -> View:
        self.progress.start()
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.progress.stop()

    def print(self, text: Text) -> None:
        self.progress.console.print(text)

    def show(self, s: JSON) -> None:
        super().show(s)
        sid = s["id"]
        if sid not in self.tasks:
            self.tasks[sid] = self.progress.add_task(self.label(s), total=None, left="")
        progress = s.get("progress") or {}
        description = f"{self.label(s)} {s['state']}"
        if s["state"] == "queued" and (place := render.queue_text(s.get("queue"))):
            description += f": {place}"
        total = progress.get("total") if s["state"] == "running" else None
        done = progress.get("done") or 0
        left = ""
        if total:
            left = self.paces.setdefault(sid, Pace()).left(done, total)
            if where := render.task_text(progress):
                description += f": {where}"
        self.progress.update(
            self.tasks[sid],
            description=description,
            total=total,
            completed=done if total else 0,
            left=left,
            visible=s["state"] not in FINAL_STATES,
        )
