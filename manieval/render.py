"""What the participant commands print: tables and times for people.

Text from the server (reasons, descriptions, log lines) is printed as plain text, never as rich
markup, so that brackets in it are shown as they are.
"""

from __future__ import annotations

import sys
from datetime import UTC, datetime
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

JSON = dict[str, Any]
STATE_STYLES = {
    "succeeded": "bold green",
    "failed": "bold red",
    "timed_out": "bold red",
    "error": "bold magenta",
    "cancelled": "yellow",
    "running": "cyan",
    "launching": "cyan",
    "queued": "dim",
}
# Piped output is read by people later (CI logs) or by programs: wide tables, not ellipses.
PIPED_WIDTH = 160


def stdout() -> Console:
    """Results: tables, logs, JSON and CSV."""
    console = Console(highlight=False)
    if not console.is_terminal:
        console = Console(highlight=False, width=PIPED_WIDTH)
    return console


def stderr() -> Console:
    """Messages and live progress."""
    return Console(stderr=True, highlight=False, soft_wrap=True)


def local_time(value: datetime | str | None) -> str:
    """A time in the user's local zone, e.g. ``2026-11-24 11:00:00 CET``."""
    if value is None:
        return "-"
    moment = datetime.fromisoformat(value) if isinstance(value, str) else value
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    local = moment.astimezone()
    return f"{local:%Y-%m-%d %H:%M:%S} {local.tzname() or local.strftime('%z')}"


def duration(seconds: float) -> str:
    """``45 s``, ``12 min``, ``3 h 5 min``, ``2 d 4 h``: rounded up, never ``0 s``."""
    total = max(1, int(seconds + 0.999))
    if total < 60:
        return f"{total} s"
    minutes = (total + 59) // 60
    if minutes < 60:
        return f"{minutes} min"
    hours, minutes = divmod(minutes, 60)
    if hours < 48:
        return f"{hours} h {minutes} min" if minutes else f"{hours} h"
    days, hours = divmod(hours, 24)
    return f"{days} d {hours} h" if hours else f"{days} d"


def time_left(elapsed_s: float, done: int, total: int) -> str:
    """``about 3 min left`` at the pace so far (''  before the first episode or after the last)."""
    if done <= 0 or done >= total or elapsed_s <= 0:
        return ""
    return f"about {duration(elapsed_s / done * (total - done))} left"


def state(name: str) -> Text:
    """A state name in its colour."""
    return Text(name, style=STATE_STYLES.get(name, ""))


def progress_text(progress: JSON | None) -> str:
    """``3/8 episodes (PickCube-v1, nominal)`` from a submission's progress, or ''."""
    if not progress or not progress.get("total"):
        return ""
    text = f"{progress.get('done') or 0}/{progress['total']} episodes"
    if where := task_text(progress):
        text += f" ({where})"
    return text


def task_text(progress: JSON | None) -> str:
    """``PickCube-v1, nominal``: the task and condition of the last episode done, or ''."""
    if not progress or not progress.get("task"):
        return ""
    condition = progress.get("condition")
    return f"{progress['task']}, {condition}" if condition else str(progress["task"])


def challenges_table(items: list[JSON]) -> Table:
    """Each challenge with its phases, open or not, and when they open or close."""
    table = Table(title="challenges")
    for column in ("challenge", "title", "phases"):
        table.add_column(column)
    for c in items:
        phases = []
        for p in c["phases"]:
            when = ""
            if p["open"] and p["closes_at"]:
                when = f", closes {local_time(p['closes_at'])}"
            elif not p["open"] and p["opens_at"]:
                when = f", opens {local_time(p['opens_at'])}"
            phases.append(f"{p['name']} ({'open' if p['open'] else 'closed'}{when})")
        table.add_row(Text(c["slug"], style="bold"), Text(c["title"]), Text("\n".join(phases)))
    return table


def submissions_table(items: list[JSON]) -> Table:
    """One row per submission: where, what, its state (with progress) and score."""
    table = Table(title="your submissions, newest first")
    for column in ("id", "challenge", "phase", "image", "state", "score", "submitted"):
        table.add_column(column, justify="right" if column in ("id", "score") else "left")
    for s in items:
        status = state(s["state"])
        if s["state"] == "running" and (shown := progress_text(s.get("progress"))):
            status.append(f" {shown}", style="dim")
        table.add_row(
            str(s["id"]),
            Text(s["challenge"]),
            Text(s["phase"]),
            Text(s["image"]),
            status,
            f"{s['score']:.3f}" if s["score"] is not None else "-",
            local_time(s["created_at"]),
        )
    return table


def queue_text(queue: object) -> str:
    """The server's "3rd in the queue, about 4 min" for a queued submission ("" if none)."""
    if not isinstance(queue, dict):
        return ""
    return str(queue.get("text") or "")


def submission_summary(s: JSON) -> Table:
    """The submission's facts as a two-column grid."""
    grid = Table.grid(padding=(0, 2))
    grid.add_column(style="bold")
    grid.add_column()
    status = state(s["state"])
    if s.get("reason"):
        status.append(f": {s['reason']}")
    rows: list[tuple[str, Text | str]] = [
        ("submission", f"{s['id']} (attempt {s['attempt']})"),
        ("challenge", Text(f"{s['challenge']} / {s['phase']}")),
        ("state", status),
    ]
    if s["state"] == "running" and (shown := progress_text(s.get("progress"))):
        rows.append(("progress", shown))
    if s["state"] == "queued" and (place := queue_text(s.get("queue"))):
        rows.append(("queue", place))
    rows += [
        ("image", Text(s["image"])),
        ("pinned", Text(s["pinned_image"])),
        ("visibility", "public" if s["public"] else "private"),
        ("submitted", local_time(s["created_at"])),
    ]
    if s.get("finished_at"):
        rows.append(("finished", local_time(s["finished_at"])))
    if s.get("score") is not None:
        rows.append(("score", f"{s['score']:.3f}"))
    if s.get("description"):
        rows.append(("description", Text(s["description"])))
    for name, value in rows:
        grid.add_row(name, value)
    return grid


def timeline(s: JSON) -> Table:
    """The submission's state changes, oldest first."""
    table = Table(title="timeline")
    for column in ("time", "attempt", "state", "reason"):
        table.add_column(column)
    for t in s.get("transitions", []):
        table.add_row(
            local_time(t["at"]), str(t["attempt"]), state(t["to_state"]), Text(t["reason"])
        )
    return table


def task_cell(r: JSON) -> str:
    """A task's result: its rate and interval when every planned episode ran, else what ran
    (a submission that ended part-way has no rate: docs/metrics.md)."""
    ran = r.get("episodes_ran", r["episodes"])
    if r.get("success_rate") is not None and ran == r["episodes"]:
        return (
            f"{r['success_rate']:.2f} [{r['ci_low']:.2f}, {r['ci_high']:.2f}]"
            f" {r['successes']}/{r['episodes']}"
        )
    if not ran:
        return f"none of {r['episodes']} ran"
    return f"{ran} of {r['episodes']} ran, {r['successes']} succeeded"


def results(s: JSON) -> Table | Text | None:
    """A submission's results as `status` and `submit --wait` print them: the table, or that
    no episode ran; None before it has any."""
    if not s["tasks"]:
        return None
    if not any(r.get("episodes_ran", r["episodes"]) for r in s["tasks"]):
        return Text("no episodes ran")
    return results_table(s)


def results_table(s: JSON) -> Table:
    """Success rate (Wilson 95% interval) per task and condition, as `manieval evaluate` shows."""
    score = f", score {s['score']:.3f}" if s.get("score") is not None else ""
    table = Table(title=f"submission {s['id']}: {s['challenge']} / {s['phase']}{score}")
    conditions = list(dict.fromkeys(r["condition"] for r in s["tasks"]))
    table.add_column("task")
    for name in conditions:
        table.add_column(name, justify="right")
    cells: dict[str, dict[str, str]] = {}
    for r in s["tasks"]:
        cells.setdefault(r["env_id"], {})[r["condition"]] = task_cell(r)
    for env_id, row in cells.items():
        table.add_row(env_id, *(row.get(c, "-") for c in conditions))
    means = s.get("conditions", {})
    table.add_row(
        Text("mean", style="bold"),
        *(Text(f"{means[c]:.3f}", style="bold") if c in means else "-" for c in conditions),
    )
    return table


def leaderboard_table(board: JSON) -> Table:
    """One leaderboard page: rank, user, score, success per task and mean per condition."""
    # The suite's order, as on the web and in the CSV (older servers: as the rows give it).
    tasks = board.get("tasks") or list(dict.fromkeys(t for r in board["items"] for t in r["tasks"]))
    conditions = board.get("conditions") or list(
        dict.fromkeys(c for r in board["items"] for c in r["conditions"])
    )
    shown = len(board["items"])
    first = (board["page"] - 1) * board["per_page"] + 1
    title = f"{board['challenge']} leaderboard ({board['phase']})"
    if board["total"] > shown:
        title += f": rows {first}-{first + shown - 1} of {board['total']}"
    table = Table(title=title)
    # A Method column only when a row names one (servers before methods: never).
    methods = any(r.get("method") for r in board["items"])
    # Tie groups (servers before them: none), beside the rank they qualify.
    groups = any(r.get("tie_group") is not None for r in board["items"])
    for column in ("rank", *(["group"] if groups else []), "user"):
        table.add_column(column, justify="left" if column == "user" else "right")
    for column in (*(["method"] if methods else []), "submission", "score"):
        table.add_column(column, justify="left" if column == "method" else "right")
    for column in (*tasks, *conditions):
        table.add_column(column, justify="right")
    for row in board["items"]:
        rank = "baseline" if row["rank"] is None else str(row["rank"])
        if row.get("tied"):
            rank = f"={rank}"  # the paired test does not separate it from the row above
        group_cells = [f"G{row['tie_group']}" if row.get("tie_group") else ""] if groups else []
        task_cells = [
            f"{row['tasks'][t]['success_rate']:.2f}" if t in row["tasks"] else "-" for t in tasks
        ]
        condition_cells = [
            f"{row['conditions'][c]:.3f}" if c in row["conditions"] else "-" for c in conditions
        ]
        method_cells = [Text(row.get("method") or "-")] if methods else []
        table.add_row(
            rank,
            *group_cells,
            _participant(row),
            *method_cells,
            str(row["submission_id"]),
            f"{row['score']:.3f}",
            *task_cells,
            *condition_cells,
        )
    return table


def _participant(row: JSON) -> Text:
    """The row's user, or its team and the member who submitted (team mode)."""
    if row.get("team"):  # the team's own name beside its display name, which anyone may pick
        shown = row.get("team_display_name") or row["team"]
        name = f" ({row['team']})" if shown != row["team"] else ""
        return Text(shown) + Text(f"{name} by {row['username']}", style="dim")
    return Text(row["username"])


def printable(text: str, *, terminal: bool) -> str:
    """A policy's log may hold terminal escape sequences: a terminal shows them defused."""
    if not terminal:
        return text
    return "".join(
        c if c in "\n\t" or (ord(c) >= 32 and ord(c) != 127) else f"\\x{ord(c):02x}" for c in text
    )


def write_raw(data: bytes | str) -> None:
    """Bytes exactly as the server sent them (CSV, JSON)."""
    raw = data.encode() if isinstance(data, str) else data
    sys.stdout.buffer.write(raw)
    if not raw.endswith(b"\n"):
        sys.stdout.buffer.write(b"\n")
    sys.stdout.flush()
