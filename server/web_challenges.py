"""Challenge and leaderboard pages: rules, phases, quota, the board and its history."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from sqlalchemy import and_, func, select
from sqlalchemy.orm import Session as DB

from server.challenges import get_challenge, get_phase, suite_of
from server.deps import DBDep, services
from server.errors import Invalid, NotFound
from server.leaderboard import Row
from server.models import Challenge, LeaderboardEntry, Phase, State, Submission, User, utcnow
from server.submissions import quota_use
from server.web_charts import ScorePoint, StepChart, best_over_time, step_chart
from server.web_support import ViewerDep, render

router = APIRouter(include_in_schema=False)

SORT_LIMIT = 2000  # rows a sorted view reads; boards are ranked by score beyond that
TOP_ROWS = 10  # rows of the board shown on the challenge page


def _phase(challenge: Challenge, name: str | None) -> Phase:
    if name is None:  # the first phase open now, else the first one
        now = utcnow()
        return next((p for p in challenge.phases if p.is_open(now)), challenge.phases[0])
    try:
        return get_phase(challenge, name)
    except Invalid:
        raise NotFound(f"challenge {challenge.slug!r} has no phase {name!r}") from None


PhaseName = Annotated[str | None, Query(max_length=32)]


@router.get("/challenges/{slug}")
def challenge_page(
    slug: str, request: Request, who: ViewerDep, db: DBDep, phase: PhaseName = None
) -> Response:
    """Description, tasks, rules, phases, quota, seed commitments, leaderboard and history."""
    challenge = get_challenge(db, slug)
    shown = _phase(challenge, phase)
    now = utcnow()
    quota = quota_use(db, who.user, challenge, now=now) if who.user is not None else None
    board = services(request).leaderboards.page(db, shown.id, 1, TOP_ROWS)
    return render(
        request,
        who,
        "challenge.html",
        challenge=challenge,
        suite=suite_of(challenge),
        phase=shown,
        now=now,
        quota=quota,
        board=board,
        chart=request.app.state.score_history.chart(db, shown),
    )


@dataclass(frozen=True)
class Column:
    key: str  # the sort key: score, user, submitted, task:<env_id>, cond:<name>
    label: str
    numeric: bool = True


def _value(row: Row, key: str) -> Any:
    kind, _, name = key.partition(":")
    if kind == "task":
        return row.tasks.get(name, {}).get("success_rate")
    if kind == "cond":
        return row.conditions.get(name)
    return {"score": row.score, "user": row.username, "submitted": row.submitted_at}.get(kind)


def sort_rows(rows: list[Row], key: str, descending: bool) -> list[Row]:
    """Rows sorted by one column; rows without a value for it go last either way."""
    present = [r for r in rows if _value(r, key) is not None]
    missing = [r for r in rows if _value(r, key) is None]
    present.sort(key=lambda r: _value(r, key), reverse=descending)
    return present + missing


@router.get("/challenges/{slug}/leaderboard")
def leaderboard_page(
    slug: str,
    request: Request,
    who: ViewerDep,
    db: DBDep,
    phase: PhaseName = None,
    sort: Annotated[str, Query(max_length=100)] = "rank",
    dir: Annotated[str, Query(pattern="^(asc|desc)$")] = "",
    page: Annotated[int, Query(ge=1, le=100_000)] = 1,
    per_page: Annotated[int, Query(ge=10, le=200)] = 50,
) -> Response:
    """The whole board: per-task success with intervals, stress conditions, sortable."""
    challenge = get_challenge(db, slug)
    shown = _phase(challenge, phase)
    suite = suite_of(challenge)
    tasks = [t.env_id for t in suite.tasks]
    stresses = [c.name for c in suite.conditions[1:]]
    columns = _columns(tasks, stresses)
    if sort not in {c.key for c in columns}:
        sort = "rank"
    descending = dir == "desc" if dir else sort not in ("user", "rank")
    rows, total = _rows(request, db, shown, sort, descending, page, per_page)
    return render(
        request,
        who,
        "leaderboard.html",
        challenge=challenge,
        phase=shown,
        tasks=tasks,
        stresses=stresses,
        columns=columns,
        rows=rows,
        total=total,
        page=page,
        per_page=per_page,
        pages=max(1, -(-total // per_page)),
        sort=sort,
        descending=descending,
        truncated=sort != "rank" and total >= SORT_LIMIT,
    )


def _columns(tasks: list[str], stresses: list[str]) -> list[Column]:
    columns = [Column("user", "Participant", numeric=False), Column("score", "Score")]
    columns += [Column(f"task:{t}", t) for t in tasks]
    columns += [Column(f"cond:{c}", c) for c in stresses]
    return [*columns, Column("submitted", "Submitted", numeric=False)]


def _rows(
    request: Request, db: DB, phase: Phase, sort: str, descending: bool, page: int, per_page: int
) -> tuple[list[Row], int]:
    """One page of the board in rank order (read by the rank index), or sorted by a column."""
    cache = services(request).leaderboards
    if sort == "rank":
        board = cache.page(db, phase.id, page, per_page)
        return board.rows, board.total
    ordered = sort_rows(cache.page(db, phase.id, 1, SORT_LIMIT).rows, sort, descending)
    return ordered[(page - 1) * per_page : page * per_page], len(ordered)


class ScoreHistory:
    """Best-score-over-time charts per (phase, board version): the version changes whenever
    something that decides the board does, so a cached chart is never stale."""

    def __init__(self, size: int = 64) -> None:
        self._charts: OrderedDict[tuple[int, int], StepChart | None] = OrderedDict()
        self._size = size
        self._lock = threading.Lock()

    def chart(self, db: DB, phase: Phase, *, now: Callable[[], Any] = utcnow) -> StepChart | None:
        key = (phase.id, phase.leaderboard_version)
        with self._lock:
            if key in self._charts:
                self._charts.move_to_end(key)
                return self._charts[key]
        baselines = db.execute(
            select(
                LeaderboardEntry.username,
                LeaderboardEntry.submission_id,
                LeaderboardEntry.score,
                LeaderboardEntry.submitted_at,
            )
            .where(LeaderboardEntry.phase_id == phase.id, LeaderboardEntry.baseline.is_(True))
            .order_by(LeaderboardEntry.score.desc())
        ).all()
        drawn = step_chart(
            best_over_time(record_points(db, phase.id)),
            now=now(),
            baselines=[
                (f"baseline {name} #{sid}", score, at) for name, sid, score, at in baselines
            ],
        )
        with self._lock:
            self._charts[key] = drawn
            while len(self._charts) > self._size:
                self._charts.popitem(last=False)
        return drawn


def record_points(db: DB, phase_id: int) -> list[ScorePoint]:
    """Public succeeded submissions that beat every earlier one: the database keeps the
    running best (a window function), so only the few records travel, however many ran."""
    eligible = and_(
        Submission.phase_id == phase_id,
        Submission.state == State.SUCCEEDED,
        Submission.public.is_(True),
        Submission.hidden.is_(False),
        Submission.baseline.is_(False),
        Submission.score.is_not(None),
    )
    order = (Submission.created_at, Submission.id)
    ranked = (
        select(
            Submission.id,
            Submission.created_at,
            Submission.score,
            User.username,
            func.max(Submission.score).over(order_by=order, rows=(None, -1)).label("before"),
        )
        .join(User, User.id == Submission.user_id)
        .where(eligible)
        .subquery()
    )
    rows = db.execute(
        select(ranked.c.id, ranked.c.created_at, ranked.c.score, ranked.c.username)
        .where((ranked.c.before.is_(None)) | (ranked.c.score > ranked.c.before))
        .order_by(ranked.c.created_at, ranked.c.id)
    ).all()
    return [
        ScorePoint(at=at, score=score, username=name, submission_id=sid)
        for sid, at, score, name in rows
    ]
