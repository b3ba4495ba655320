"""The leaderboard API, ``/api/v1/challenges/{slug}/leaderboard``: JSON or CSV, cached."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi import Path as FastAPIPath
from starlette.concurrency import run_in_threadpool

from server.accounts.deps import CallerDep
from server.kit.deps import DBDep, PageNo, PerPage
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import SLUG_PATTERN
from server.leaderboard.deps import BoardServices, services
from server.leaderboard.late import post_deadline_board
from server.leaderboard.paper import MEDIA_TYPE, SUFFIX, PaperFormat, paper_table, provenance
from server.leaderboard.schemas import LateRowOut, LeaderboardOut, PostDeadlineOut
from server.leaderboard.snapshot import Snapshot
from server.leaderboard.visibility import as_seen_by_caller

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)


@router.get(
    "/challenges/{slug}/leaderboard",
    tags=["challenges"],
    response_model=LeaderboardOut,
    responses={
        200: {
            "content": {
                media: {"schema": {"type": "string"}}
                for media in ("text/csv", *MEDIA_TYPE.values())
            }
        }
    },
)
async def leaderboard(
    slug: Annotated[str, FastAPIPath(max_length=64, pattern=SLUG_PATTERN)],
    request: Request,
    phase: Annotated[str, Query(max_length=32)] = "dev",
    page: PageNo = 1,
    per_page: PerPage = 50,
    format: Literal["json", "csv", "markdown", "latex"] = "json",
    version: Annotated[int | None, Query(ge=1, le=1_000_000)] = None,
) -> Response:
    """Best public submission per user (per team, in a challenge with team mode on), by score
    (equal scores: the earlier submission first).

    Each row carries its score's 95% interval, its `tie_group` (consecutive rows that McNemar's
    exact test on their paired episodes, Holm-corrected over the board at the phase's level,
    does not separate share one) and `tied` (in the group of the ranked row above):
    docs/metrics.md, "Paired significance". `tasks` and `conditions` list the suite's in its
    order, which every row's dictionaries and the CSV's columns follow. `markdown` and `latex`
    give the page as a table for a paper: per-task success and score with intervals, tie
    groups, and a line of provenance (the result documents' suites and versions).

    The most read page of the service: each phase's whole board is kept in memory, brought up
    to date from the rows that changed (at most once every `MANIEVAL_LEADERBOARD_MAX_AGE`
    seconds while it changes), and every page, size and format is cut from it, so a page
    costs neither a thread nor a query.

    A phase whose board is hidden (its rules' `board: hidden`) shows, until an organizer
    publishes it, only the caller's own rows (their team's in team mode), unranked; admins see
    it whole (docs/server.md, "Challenge rules").

    `version` reads an earlier board version: each re-evaluation of the phase (after a change
    of its suite or evaluator) publishes a new one, and the earlier ones stay readable; none
    given, the current one (docs/server.md, "Re-evaluation").
    """
    svc = services(request)
    board = svc.boards.fresh(slug, phase, version)
    if board is None:
        board = await run_in_threadpool(
            lambda: svc.boards.current(svc.sessions, slug=slug, phase=phase, board_version=version)
        )
    if board.hidden:  # not published: who asks decides which rows they see
        board = await run_in_threadpool(_as_seen, svc, board, request)
    if format in ("markdown", "latex"):
        paper: PaperFormat = "markdown" if format == "markdown" else "latex"
        text = await run_in_threadpool(_paper, svc, board, paper, page, per_page)
        disposition = f'attachment; filename="{slug}-{phase}.{SUFFIX[paper]}"'
        return Response(
            text, media_type=MEDIA_TYPE[paper], headers={"Content-Disposition": disposition}
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


def _as_seen(svc: BoardServices, board: Snapshot, request: Request) -> Snapshot:
    with svc.sessions() as db:
        return as_seen_by_caller(db, board, request)


def _paper(
    svc: BoardServices, board: Snapshot, format: PaperFormat, page: int, per_page: int
) -> str:
    shown = board.rows[(page - 1) * per_page : page * per_page]
    with svc.sessions() as db:
        line = provenance(db, submission_ids=[s.submission_id for s in shown], alpha=board.alpha)
    return paper_table(board, format=format, page=page, per_page=per_page, line=line)


@router.get("/challenges/{slug}/post-deadline", tags=["challenges"])
def post_deadline(
    slug: Annotated[str, FastAPIPath(max_length=64, pattern=SLUG_PATTERN)],
    who: CallerDep,
    db: DBDep,
    phase: Annotated[str, Query(max_length=32)] = "test",
) -> PostDeadlineOut:
    """The phase's post-deadline board (a phase whose rules say `after_close: post_deadline`):
    what was submitted after it closed, ranked apart from the official board."""
    rows = post_deadline_board(db, slug=slug, phase=phase, viewer=who.user)
    return PostDeadlineOut(
        challenge=slug, phase=phase, items=[LateRowOut(**row.__dict__) for row in rows]
    )
