"""The leaderboard page: per-task success with intervals, stress conditions, sortable.

Its rows are cut from the phase's snapshot (server/leaderboard/snapshot.py), the one the API
serves from. Its content (everything under the site's header) is the same for every viewer,
so it is rendered once per distinct content and kept in a bounded LRU (`BoardPages`); the
header, which says who is logged in and carries their form token, is rendered per request.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from markupsafe import Markup
from sqlalchemy.orm import Session as DB

from server.accounts.deps import ViewerDep
from server.challenges.service import get_challenge, shown_phase
from server.kit.deps import DBDep
from server.kit.pages import render, templates
from server.leaderboard.columns import board_columns
from server.leaderboard.deps import services
from server.leaderboard.late import post_deadline_board
from server.leaderboard.service import Board, Row, suite_columns
from server.leaderboard.snapshot import Snapshot
from server.leaderboard.visibility import as_seen_by
from server.models import User, utcnow

router = APIRouter(include_in_schema=False)

SORT_LIMIT = 2000  # rows a sorted view reads; boards are ranked by score beyond that


def snapshot(
    request: Request,
    db: DB,
    *,
    slug: str,
    phase: str,
    viewer: User | None,
    board_version: int | None = None,
) -> Snapshot:
    """The phase's board (of `board_version`; None: the current one) as the API serves it
    (confirmed in the caller's session when due), as `viewer` may see it (a hidden board)."""
    boards = services(request).boards
    board = boards.fresh(slug, phase, board_version) or boards.current_in(
        db, slug=slug, phase=phase, board_version=board_version
    )
    return as_seen_by(db, board, user=viewer)


def top_rows(
    request: Request, db: DB, *, slug: str, phase: str, count: int, viewer: User | None
) -> Board:
    """The board's first rows in rank order, and how many it has (the challenge page's)."""
    board = snapshot(request, db, slug=slug, phase=phase, viewer=viewer)
    return Board(rows=[board.row(i) for i in range(min(count, board.total))], total=board.total)


def sort_value(key: str) -> Callable[[Row], Any]:
    """What a row is sorted by under a column's sort key (None: it has no value there)."""
    kind, _, name = key.partition(":")
    if kind == "task":
        return lambda row: row.tasks.get(name, {}).get("success_rate")
    if kind == "cond":
        return lambda row: row.conditions.get(name)
    return {
        "score": lambda row: row.score,
        "user": lambda row: row.participant,
        "submitted": lambda row: row.submitted_at,
    }[kind]


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
    version: Annotated[int | None, Query(ge=1, le=1_000_000)] = None,
) -> Response:
    """The whole board (of board version `version`; None: the current one): per-task success
    with intervals, stress conditions, sortable."""
    challenge = get_challenge(db, slug=slug)
    shown = shown_phase(challenge, name=phase)
    tasks, conditions = suite_columns(challenge)
    stresses = conditions[1:]
    columns = board_columns(tasks, stresses)
    if sort not in {c.key for c in columns}:
        sort = "rank"
    descending = dir == "desc" if dir else sort not in ("user", "rank")
    board = snapshot(
        request, db, slug=challenge.slug, phase=shown.name, viewer=who.user, board_version=version
    )
    places: Sequence[int]
    if sort == "rank":
        places, total = range(board.total)[(page - 1) * per_page : page * per_page], board.total
    else:
        order = board.order(sort_value(sort), sort, descending, SORT_LIMIT)
        places, total = order[(page - 1) * per_page : page * per_page], len(order)
    context = {
        "challenge": challenge,
        "phase": shown,
        "tasks": tasks,
        "stresses": stresses,
        "columns": columns,
        "total": total,
        "page": page,
        "per_page": per_page,
        "pages": max(1, -(-total // per_page)),
        "sort": sort,
        "descending": descending,
        "truncated": sort != "rank" and total >= SORT_LIMIT,
        "alpha": board.alpha,
        "board_version": board.board_version,
        "current_version": max(shown.board_version, board.board_version),
        "pending_version": shown.pending_board_version,
        "version_asked": version,
    }
    # What the content shows, all of it: a stored row's serial always means the same row
    # (server/leaderboard/stored.py), the rest is the challenge's and the address's.
    key = (
        challenge.slug,
        challenge.title,
        tuple((p.id, p.name) for p in challenge.phases),
        shown.id,
        shown.name,
        tuple(tasks),
        tuple(stresses),
        tuple((board.rows[i].serial, board.place(i)) for i in places),
        *(context[k] for k in ("total", "page", "per_page", "sort", "descending", "alpha")),
        *(context[k] for k in ("board_version", "current_version", "pending_version")),
        version,
    )

    def content() -> str:
        rows = [board.row(i) for i in places]
        cells = templates.get_template("_board_row.html").module.cells  # type: ignore[attr-defined]
        columns = (tuple(tasks), tuple(stresses))

        def cells_of(row: Row) -> Callable[[], str]:
            return lambda: str(cells(row, tasks, stresses))

        row_cells = [
            Markup(board.rows[i].html(columns, cells_of(row)))
            for i, row in zip(places, rows, strict=True)
        ]
        return templates.get_template("_leaderboard_main.html").render(
            rows=rows, row_cells=row_cells, **context
        )

    # A page past the end is not kept: any address could otherwise push real pages out.
    main = services(request).board_pages.get(key, content) if places else content()
    return render(
        request,
        who,
        "leaderboard.html",
        challenge=challenge,
        phase=shown,
        board_main=Markup(main),
        may_reevaluate=shown.pending_board_version is None and board.total > 0,
        phase_open=shown.is_open(utcnow()),
    )


@router.get("/challenges/{slug}/post-deadline")
def post_deadline_page(
    slug: str,
    request: Request,
    who: ViewerDep,
    db: DBDep,
    phase: Annotated[str, Query(max_length=32)] = "test",
) -> Response:
    """The phase's post-deadline board: what was submitted after it closed, ranked apart."""
    challenge = get_challenge(db, slug=slug)
    shown = shown_phase(challenge, name=phase)
    rows = post_deadline_board(db, slug=challenge.slug, phase=shown.name, viewer=who.user)
    return render(request, who, "post_deadline.html", challenge=challenge, phase=shown, rows=rows)
