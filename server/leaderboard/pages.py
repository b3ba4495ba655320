"""The leaderboard page: per-task success with intervals, stress conditions, sortable."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.challenges.service import get_challenge, shown_phase, suite_of
from server.kit.deps import DBDep, services
from server.kit.pages import ViewerDep, render
from server.leaderboard.columns import board_columns
from server.leaderboard.service import Row
from server.models import Phase

router = APIRouter(include_in_schema=False)

SORT_LIMIT = 2000  # rows a sorted view reads; boards are ranked by score beyond that


def _value(row: Row, key: str) -> Any:
    kind, _, name = key.partition(":")
    if kind == "task":
        return row.tasks.get(name, {}).get("success_rate")
    if kind == "cond":
        return row.conditions.get(name)
    return {"score": row.score, "user": row.participant, "submitted": row.submitted_at}.get(kind)


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
    phase: Annotated[str | None, Query(max_length=32)] = None,
    sort: Annotated[str, Query(max_length=100)] = "rank",
    dir: Annotated[str, Query(pattern="^(asc|desc)$")] = "",
    page: Annotated[int, Query(ge=1, le=100_000)] = 1,
    per_page: Annotated[int, Query(ge=10, le=200)] = 50,
) -> Response:
    """The whole board: per-task success with intervals, stress conditions, sortable."""
    challenge = get_challenge(db, slug=slug)
    shown = shown_phase(challenge, name=phase)
    suite = suite_of(challenge)
    tasks = [t.env_id for t in suite.tasks]
    stresses = [c.name for c in suite.conditions[1:]]
    columns = board_columns(tasks, stresses)
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


def _rows(
    request: Request, db: DB, phase: Phase, sort: str, descending: bool, page: int, per_page: int
) -> tuple[list[Row], int]:
    """One page of the board in rank order (read by the rank index), or sorted by a column."""
    cache = services(request).leaderboards
    if sort == "rank":
        board = cache.page(db, phase_id=phase.id, page=page, per_page=per_page)
        return board.rows, board.total
    ordered = sort_rows(
        cache.page(db, phase_id=phase.id, page=1, per_page=SORT_LIMIT).rows, sort, descending
    )
    return ordered[(page - 1) * per_page : page * per_page], len(ordered)
