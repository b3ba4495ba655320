"""Chart geometry: pure functions, checked number by number."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

from server.challenges.charts import (
    BAR_LABEL_WIDTH,
    ScorePoint,
    TaskSuccess,
    best_over_time,
    step_chart,
    success_bars,
)

T0 = datetime(2026, 1, 1, tzinfo=UTC)


def point(hours: float, score: float, sid: int) -> ScorePoint:
    return ScorePoint(
        at=T0 + timedelta(hours=hours), score=score, username=f"u{sid}", submission_id=sid
    )


def test_success_bars_scale_rates_and_intervals_and_group_by_condition() -> None:
    rows = [
        TaskSuccess("nominal", "PickCube-v1", 3, 4, 0.75, 0.3, 0.95),
        TaskSuccess("nominal", "PushCube-v1", 0, 4, 0.0, 0.0, 0.49),
        TaskSuccess("obs_noise", "PickCube-v1", 4, 4, 1.0, 0.51, 1.0),
    ]
    chart = success_bars(rows)
    plot = chart.plot_width
    assert [b.width for b in chart.bars] == [round(0.75 * plot, 1), 0.0, float(plot)]
    assert chart.bars[0].low_x == round(BAR_LABEL_WIDTH + 0.3 * plot, 1)
    assert chart.bars[2].high_x == BAR_LABEL_WIDTH + plot
    assert [name for _, name in chart.groups] == ["nominal", "obs_noise"]
    assert chart.bars[0].y < chart.bars[1].y < chart.bars[2].y < chart.height
    assert "3 of 4 (75%; 95% interval 30% to 95%)" in chart.bars[0].title


def test_best_over_time_keeps_the_points_that_raised_the_best_score() -> None:
    points = [
        point(3, 0.5, 3),
        point(1, 0.2, 1),
        point(2, 0.1, 2),
        point(4, 0.5, 4),
        point(5, 0.9, 5),
    ]
    assert [p.submission_id for p in best_over_time(points)] == [1, 3, 5]
    assert best_over_time([]) == []


def test_step_chart_draws_a_step_line_to_now_with_baselines() -> None:
    records = [point(0, 0.25, 1), point(10, 0.75, 2)]
    chart = step_chart(
        records, now=T0 + timedelta(hours=20), baselines=[("baseline random #3", 0.5, T0)]
    )
    assert chart is not None
    first, second = chart.markers
    assert first.x == chart.left
    assert second.x == (chart.left + chart.right) / 2
    assert first.y > second.y  # higher scores are drawn higher
    assert chart.path == f"M{first.x} {first.y} H{second.x} V{second.y} H{float(chart.right)}"
    ys = [y for y, _ in chart.y_ticks]
    assert chart.baselines == [((ys[0] + ys[-1]) / 2, "baseline random #3")]


def test_step_chart_shows_baselines_alone_and_nothing_without_data() -> None:
    chart = step_chart([], now=T0 + timedelta(days=3), baselines=[("baseline a #1", 1.0, T0)])
    assert chart is not None
    assert chart.path == ""
    assert chart.markers == []
    assert chart.baselines == [(chart.top, "baseline a #1")]
    assert [label for _, label in chart.x_ticks] == ["2026-01-01", "2026-01-02", "2026-01-04"]
    assert step_chart([], now=T0) is None


def test_step_chart_axis_ends_now_and_widens_a_short_history_into_the_past() -> None:
    now = T0 + timedelta(minutes=10)
    chart = step_chart([point(0, 0.5, 1)], now=now)
    assert chart is not None
    assert chart.path.endswith(f"H{float(chart.right)}")  # the line reaches now, the right edge
    (x_first, first), _, (x_last, last) = chart.x_ticks
    assert (x_first, x_last) == (chart.left, chart.right)
    assert last == "01-01 00:10"  # the axis ends at now, not an hour later
    assert first == "12-31 23:10"
    assert chart.markers[0].x > chart.left  # the point sits 50 minutes into the hour shown


def test_step_chart_ticks_are_utc_whatever_the_zone_of_now() -> None:
    paris = timezone(timedelta(hours=1))
    now = (T0 + timedelta(minutes=30)).astimezone(paris)  # 01:30 in Paris
    chart = step_chart([point(0, 0.5, 1)], now=now)
    assert chart is not None
    assert chart.x_ticks[-1][1] == "01-01 00:30"
