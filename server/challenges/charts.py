"""Charts as geometry for inline SVG: pure functions, no I/O, drawn by `_charts.html`.

Rendering on the server keeps the pages free of chart libraries and scripts; the numbers the
charts show are also in the tables next to them (and in each shape's <title>).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta


@dataclass(frozen=True)
class TaskSuccess:
    condition: str
    env_id: str
    successes: int
    episodes: int
    rate: float
    low: float
    high: float


@dataclass(frozen=True)
class Bar:
    label: str
    y: float
    width: float
    low_x: float
    high_x: float
    title: str


@dataclass(frozen=True)
class BarChart:
    width: int
    height: int
    left: int
    plot_width: int
    bar_height: int
    bars: list[Bar]
    groups: list[tuple[float, str]]  # y and name of each condition's heading
    ticks: list[tuple[float, str]]  # x and label


BAR_CHART_WIDTH = 640
BAR_LABEL_WIDTH = 170
BAR_HEIGHT = 18
BAR_GAP = 8
GROUP_HEADING = 22
AXIS_HEIGHT = 22


def success_bars(rows: Sequence[TaskSuccess]) -> BarChart:
    """Horizontal bars of success rate per task, grouped by condition, with the interval."""
    plot = BAR_CHART_WIDTH - BAR_LABEL_WIDTH - 16
    y = 0.0
    bars: list[Bar] = []
    groups: list[tuple[float, str]] = []
    condition: str | None = None
    for row in rows:
        if row.condition != condition:
            condition = row.condition
            y += GROUP_HEADING
            groups.append((y - 7, row.condition))
        bars.append(
            Bar(
                label=row.env_id,
                y=y,
                width=round(_clamp(row.rate) * plot, 1),
                low_x=round(BAR_LABEL_WIDTH + _clamp(row.low) * plot, 1),
                high_x=round(BAR_LABEL_WIDTH + _clamp(row.high) * plot, 1),
                title=(
                    f"{row.condition} / {row.env_id}: {row.successes} of {row.episodes} "
                    f"({row.rate:.0%}; 95% interval {row.low:.0%} to {row.high:.0%})"
                ),
            )
        )
        y += BAR_HEIGHT + BAR_GAP
    ticks = [(BAR_LABEL_WIDTH + f * plot, f"{f:.0%}") for f in (0, 0.25, 0.5, 0.75, 1)]
    return BarChart(
        width=BAR_CHART_WIDTH,
        height=int(y + AXIS_HEIGHT),
        left=BAR_LABEL_WIDTH,
        plot_width=plot,
        bar_height=BAR_HEIGHT,
        bars=bars,
        groups=groups,
        ticks=ticks,
    )


@dataclass(frozen=True)
class ScorePoint:
    at: datetime
    score: float
    username: str
    submission_id: int


def best_over_time(points: Iterable[ScorePoint]) -> list[ScorePoint]:
    """The points that raised the best score, in time order (ties keep the earlier one)."""
    records: list[ScorePoint] = []
    for point in sorted(points, key=lambda p: (p.at, p.submission_id)):
        if not records or point.score > records[-1].score:
            records.append(point)
    return records


@dataclass(frozen=True)
class Marker:
    x: float
    y: float
    point: ScorePoint


@dataclass(frozen=True)
class StepChart:
    width: int
    height: int
    left: int
    right: int
    top: int
    bottom: int
    path: str
    markers: list[Marker]
    x_ticks: list[tuple[float, str]]
    y_ticks: list[tuple[float, str]]
    baselines: list[tuple[float, str]]


STEP_WIDTH, STEP_HEIGHT = 640, 220
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM = 44, 16, 12, 28
MIN_SPAN = timedelta(hours=1)  # the narrowest time axis drawn


def step_chart(
    records: Sequence[ScorePoint],
    *,
    now: datetime,
    baselines: Sequence[tuple[str, float, datetime]] = (),
) -> StepChart | None:
    """The best score as a step line from the first record until `now`, and each baseline
    (name, score, submitted at) as a level line; None when there is neither.

    The time axis (UTC) ends at `now` (or at the last point, should one be later) and never
    beyond: a short history is widened to `MIN_SPAN` into the past, not into the future."""
    if not records and not baselines:
        return None
    times = [p.at for p in records] + [at for _, _, at in baselines]
    end = max([now, *times])
    start = min([*times, end - MIN_SPAN])
    span = (end - start).total_seconds()
    right, bottom = STEP_WIDTH - MARGIN_RIGHT, STEP_HEIGHT - MARGIN_BOTTOM

    def x(at: datetime) -> float:
        return round(MARGIN_LEFT + (at - start).total_seconds() / span * (right - MARGIN_LEFT), 1)

    def y(score: float) -> float:
        return round(bottom - _clamp(score) * (bottom - MARGIN_TOP), 1)

    markers = [Marker(x=x(p.at), y=y(p.score), point=p) for p in records]
    path = ""
    if markers:
        path = f"M{markers[0].x} {markers[0].y}"
        for marker in markers[1:]:
            path += f" H{marker.x} V{marker.y}"
        path += f" H{x(end)}"
    fmt = "%Y-%m-%d" if span > 2 * 86400 else "%m-%d %H:%M"
    ticks = [start + (end - start) * f for f in (0, 0.5, 1)]
    return StepChart(
        width=STEP_WIDTH,
        height=STEP_HEIGHT,
        left=MARGIN_LEFT,
        right=right,
        top=MARGIN_TOP,
        bottom=bottom,
        path=path,
        markers=markers,
        x_ticks=[(x(at), at.astimezone(UTC).strftime(fmt)) for at in ticks],
        y_ticks=[(y(f), f"{f:.2f}") for f in (0, 0.25, 0.5, 0.75, 1)],
        baselines=[(y(score), name) for name, score, _ in baselines],
    )


def _clamp(value: float) -> float:
    return min(1.0, max(0.0, value))
