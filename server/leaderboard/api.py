"""The leaderboard API, ``/api/v1/challenges/{slug}/leaderboard``: JSON or CSV, cached."""

from __future__ import annotations

import csv
import io
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi import Path as FastAPIPath
from starlette.concurrency import run_in_threadpool

from server.kit.deps import PageNo, PerPage, Services, services
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import SLUG_PATTERN
from server.leaderboard.schemas import LeaderboardOut, LeaderboardRowOut
from server.leaderboard.service import PageKey, Rendered, board_version, column_order

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

    The most read page of the service: rendered bytes are cached per board version and
    re-validated against the database at most every `MANIEVAL_LEADERBOARD_MAX_AGE` seconds, so
    a hit costs neither a thread nor a query.
    """
    svc = services(request)
    key = (slug, phase, page, per_page, format)
    rendered = svc.leaderboard_pages.fresh(key)
    if rendered is None:
        rendered = await run_in_threadpool(_render_leaderboard, svc, key)
    return Response(rendered.body, media_type=rendered.media_type, headers=rendered.headers)


def _render_leaderboard(svc: Services, key: PageKey) -> Rendered:
    slug, phase, page, per_page, format = key
    with svc.sessions() as db:
        phase_id, version = board_version(db, slug=slug, phase=phase)
        if (same := svc.leaderboard_pages.revalidate(key, version)) is not None:
            return same
        board = svc.leaderboards.page(db, phase_id=phase_id, page=page, per_page=per_page)
        tasks, conditions = column_order(db, slug=slug)
    out = LeaderboardOut(
        challenge=slug,
        phase=phase,
        page=page,
        per_page=per_page,
        total=board.total,
        tasks=tasks,
        conditions=conditions,
        items=[
            LeaderboardRowOut(**row.in_order(tasks=tasks, conditions=conditions).__dict__)
            for row in board.rows
        ],
    )
    if format == "csv":
        rendered = Rendered(
            version=version,
            body=_leaderboard_csv(out).encode(),
            media_type="text/csv; charset=utf-8",
            headers={"Content-Disposition": f'attachment; filename="{slug}-{phase}.csv"'},
        )
    else:
        rendered = Rendered(
            version=version, body=out.model_dump_json().encode(), media_type="application/json"
        )
    svc.leaderboard_pages.store(key, rendered)
    return rendered


def _leaderboard_csv(board: LeaderboardOut) -> str:
    """The page as CSV, tasks and conditions in the suite's order (as on the web)."""
    tasks, conditions = board.tasks, board.conditions
    buf = io.StringIO()
    writer = csv.writer(buf)
    header = ["rank", "username", "baseline", "score", "score_ci_low", "score_ci_high", "tied"]
    header += ["submitted_at", "submission_id", "team", "team_display_name", "method"]
    header += ["paper_url", "code_url"]
    header += [f"{t} success" for t in tasks] + [f"{t} ci_low" for t in tasks]
    header += [f"{t} ci_high" for t in tasks] + [f"condition {c}" for c in conditions]
    writer.writerow(header)
    for row in board.items:
        cells: list[object] = [
            row.rank if row.rank is not None else "",
            _csv_safe(row.username),
            row.baseline,
            f"{row.score:.4f}",
            f"{row.score_ci_low:.4f}" if row.score_ci_low is not None else "",
            f"{row.score_ci_high:.4f}" if row.score_ci_high is not None else "",
            row.tied,
            row.submitted_at.isoformat(),
            row.submission_id,
            row.team or "",
            _csv_safe(row.team_display_name or ""),
            _csv_safe(row.method or ""),
            row.paper_url or "",
            row.code_url or "",
        ]
        for key in ("success_rate", "ci_low", "ci_high"):
            cells += [f"{row.tasks[t][key]:.4f}" if t in row.tasks else "" for t in tasks]
        cells += [f"{row.conditions[c]:.4f}" if c in row.conditions else "" for c in conditions]
        writer.writerow(cells)
    return buf.getvalue()


def _csv_safe(text: str) -> str:
    """Spreadsheets run cells starting with = + - @ as formulas: defuse them."""
    return "'" + text if text[:1] in ("=", "+", "-", "@") else text
