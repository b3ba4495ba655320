"""Following a submission until it ends: on a terminal a live progress bar (episodes done of
the total, from the submission's progress), elsewhere one plain line per change."""

from __future__ import annotations

import time
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


def follow(client: Client, submission_id: int, *, interval: float = POLL_SECONDS) -> JSON:
    """Poll until the submission ends and return its final detail (Ctrl-C propagates)."""
    console = render.stderr()
    view: View = LiveView(console) if console.is_terminal else LineView(console)
    misses = 0
    with view:
        while True:
            try:
                submission = client.submission(submission_id)
            except ClientError as exc:
                if not _transient(exc) or misses >= MAX_MISSES:
                    raise
                misses += 1
                view.note(f"no answer from the server ({exc}); trying again")
                time.sleep(interval * 2**misses)
                continue
            misses = 0
            view.show(submission)
            if submission["state"] in FINAL_STATES:
                return submission
            time.sleep(interval)


def _transient(exc: ClientError) -> bool:
    return isinstance(exc, Unreachable) or (
        isinstance(exc, ApiError) and (exc.status >= 500 or exc.status == 429)
    )


def state_line(s: JSON) -> Text:
    """``submission 7: running`` with the reason when it has ended."""
    line = Text(f"submission {s['id']}: ") + render.state(s["state"])
    if s["state"] in FINAL_STATES and s.get("reason"):
        line.append(f" ({s['reason']})")
    return line


class View:
    def __init__(self, console: Console) -> None:
        self.console = console
        self.last_state: str | None = None

    def __enter__(self) -> View:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        return None

    def show(self, s: JSON) -> None:
        if s["state"] != self.last_state:
            self.last_state = s["state"]
            self.console.print(state_line(s))

    def note(self, text: str) -> None:
        self.console.print(Text(text, style="yellow"))


class LineView(View):
    """For logs and pipes: a line when the state or the episode count changes."""

    def __init__(self, console: Console) -> None:
        super().__init__(console)
        self.last_progress = ""

    def show(self, s: JSON) -> None:
        super().show(s)
        shown = render.progress_text(s.get("progress")) if s["state"] == "running" else ""
        if s["state"] == "queued":
            shown = render.queue_text(s.get("queue"))
        if shown and shown != self.last_progress:
            self.last_progress = shown
            self.console.print(Text(f"submission {s['id']}: {shown}"))


class LiveView(View):
    """For a terminal: state changes printed above a live bar of episodes done."""

    def __init__(self, console: Console) -> None:
        super().__init__(console)
        self.progress = Progress(
            SpinnerColumn(),
            TextColumn("{task.description}", markup=False),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("episodes"),
            TimeElapsedColumn(),
            console=console,
            transient=True,
        )
        self.task: TaskID | None = None

    def __enter__(self) -> View:
        self.progress.start()
        self.task = self.progress.add_task("waiting", total=None)
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.progress.stop()

    def show(self, s: JSON) -> None:
        super().show(s)
        assert self.task is not None
        progress = s.get("progress") or {}
        description = s["state"]
        if s["state"] == "queued" and (place := render.queue_text(s.get("queue"))):
            description += f": {place}"
        if s["state"] == "running" and progress.get("task"):
            description += f": {progress['task']} ({progress.get('condition', '')})"
        total = progress.get("total") if s["state"] == "running" else None
        self.progress.update(
            self.task,
            description=description,
            total=total,
            completed=progress.get("done", 0) if total else 0,
        )

    def note(self, text: str) -> None:
        self.progress.console.print(Text(text, style="yellow"))
