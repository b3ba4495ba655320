"""The home page: the challenges. A challenge's own page shows the top of its leaderboard and
its best score over time, so it lives above both, with the leaderboard's pages
(server/leaderboard/challenge_page.py)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse, Response

from server.accounts.deps import ViewerDep
from server.challenges.prose import summary
from server.challenges.service import all_challenges
from server.kit.deps import DBDep
from server.kit.pages import render
from server.models import utcnow

router = APIRouter(include_in_schema=False)


@router.get("/")
def home(request: Request, who: ViewerDep, db: DBDep) -> Response:
    """The challenges: those open for submissions first."""
    now = utcnow()
    challenges = all_challenges(db)
    open_now = [c for c in challenges if any(p.is_open(now) for p in c.phases)]
    others = [c for c in challenges if c not in open_now]
    summaries = {c.slug: summary(c.description) for c in challenges}
    return render(
        request,
        who,
        "home.html",
        open_now=open_now,
        others=others,
        now=now,
        summaries=summaries,
    )


@router.get("/favicon.ico")
def favicon() -> Response:
    return RedirectResponse("/static/favicon.svg", status_code=301)
