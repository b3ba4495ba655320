"""The web pages: server-rendered Jinja2 templates (`web/templates`) on the domain code.

`install(app)` adds them to the FastAPI app: the routers of each area, `/static` and the
redirect to the login page. Pages call the same services as the API (no HTTP round trip);
they are left out of the OpenAPI document, which describes the API only.
"""

from __future__ import annotations

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from sqlalchemy import select
from sqlalchemy.orm import selectinload

from server import web_accounts, web_challenges, web_events, web_submissions, web_submit
from server.deps import DBDep
from server.models import Challenge, utcnow
from server.web_support import (
    STATIC_DIR,
    LoginRequired,
    ViewerDep,
    login_redirect,
    render,
)

router = APIRouter(include_in_schema=False)


def install(app: FastAPI) -> None:
    """Serve the pages and their static files from `app`."""
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.add_exception_handler(LoginRequired, login_redirect)
    app.state.score_history = web_challenges.ScoreHistory()
    app.state.event_timing = web_events.StreamTiming()
    app.state.event_slots = web_events.StreamSlots()
    areas = (web_accounts, web_challenges, web_submit, web_submissions, web_events)
    app.include_router(router)
    for area in areas:
        app.include_router(area.router)


@router.get("/")
def home(request: Request, who: ViewerDep, db: DBDep) -> Response:
    """The challenges: those open for submissions first."""
    now = utcnow()
    challenges = db.scalars(
        select(Challenge).options(selectinload(Challenge.phases)).order_by(Challenge.id)
    ).all()
    open_now = [c for c in challenges if any(p.is_open(now) for p in c.phases)]
    others = [c for c in challenges if c not in open_now]
    return render(request, who, "home.html", open_now=open_now, others=others, now=now)


@router.get("/favicon.ico")
def favicon() -> Response:
    return RedirectResponse("/static/favicon.svg", status_code=301)
