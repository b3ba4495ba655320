"""The leaderboard API, ``/api/v1/challenges/{slug}/leaderboard``: JSON or CSV, cached."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi import Path as FastAPIPath
from starlette.concurrency import run_in_threadpool

from server.kit.deps import PageNo, PerPage
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import SLUG_PATTERN
from server.leaderboard.deps import services
from server.leaderboard.schemas import LeaderboardOut

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)


@router.get(
    "/challenges/{slug}/leaderboard",
    tags=["challenges"],
    response_model=LeaderboardOut,
    responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}}}},
)
async def leaderboard(
    slug: Annotated[str, FastAPIPath(max_length=64, pattern=SLUG_PATTERN)],
    request: Request,
    phase: Annotated[str, Query(max_length=32)] = "dev",
    page: PageNo = 1,
    per_page: PerPage = 50,
    format: Literal["json", "csv"] = "json",
) -> Response:
    """Best public submission per user (per team, in a challenge with team mode on), by score
    (equal scores: the earlier submission first).

    Each row carries its score's 95% interval and `tied`: whether that interval overlaps the
    one of the ranked row above (docs/metrics.md, "How ties are decided"). `tasks` and
    `conditions` list the suite's in its order, which every row's dictionaries and the CSV's
    columns follow.

    The most read page of the service: each phase's whole board is kept in memory, brought up
    to date from the rows that changed (at most once every `MANIEVAL_LEADERBOARD_MAX_AGE`
    seconds while it changes), and every page, size and format is cut from it, so a page
    costs neither a thread nor a query.
    """
    svc = services(request)
    board = svc.boards.fresh(slug, phase)
    if board is None:
        board = await run_in_threadpool(
            lambda: svc.boards.current(svc.sessions, slug=slug, phase=phase)
        )
    if board.ready(page, per_page, format):
        body = board.body(page, per_page, format)  # every row serialized: a join, no thread
    else:
        body = await run_in_threadpool(board.body, page, per_page, format)
    if format == "csv":
        disposition = f'attachment; filename="{slug}-{phase}.csv"'
        return Response(
            body,
            media_type="text/csv; charset=utf-8",
            headers={"Content-Disposition": disposition},
        )
    return Response(body, media_type="application/json")
