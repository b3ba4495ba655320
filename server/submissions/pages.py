"""A submission's page: live timeline, results with intervals, episodes, log, videos, and the
owner's and administrators' actions.

Who sees what is the API's rule (`server.submissions.service`): a submission others may not see is a
404; its episodes and log are for its owner and administrators only, its episode videos for
whoever sees it (`server.submissions.videos`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import urlencode

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.accounts.deps import PostedDep, ViewerDep
from server.challenges.charts import TaskSuccess, success_bars
from server.challenges.service import close_phase, get_challenge, publish_board, shown_phase
from server.kit.deps import DBDep, Id
from server.kit.pages import Viewer, admin_signed_in, redirect, render, signed_in
from server.models import EpisodeResultRow, State, Submission, utcnow
from server.submissions.attempts import attempts_of
from server.submissions.deps import services
from server.submissions.final import mark_final, markable
from server.submissions.moderation import Moderation, moderate, rerun
from server.submissions.position import queue_out
from server.submissions.reevaluation import reevaluate, reevaluations_of
from server.submissions.service import (
    cancel,
    condition_means,
    edit,
    episode_rows,
    get_owned,
    get_visible,
    owned_or_admin,
    provenance_of,
    task_rows,
    transitions_of,
    visible_to,
)
from server.submissions.trajectories import may_download_trajectories, trajectories_of
from server.submissions.video_store import VideoStore
from server.submissions.videos import video_store, videos_of

router = APIRouter(include_in_schema=False)

EPISODES_PER_PAGE = 100
ENDED_BADLY = frozenset({State.FAILED, State.ERROR, State.TIMED_OUT, State.CANCELLED})
PageNo = Annotated[int, Query(ge=1, le=100_000)]


@dataclass(frozen=True)
class Evaluation:
    """One evaluation of a board entry on one board version (docs/server.md, Re-evaluation)."""

    submission: Submission
    this: bool
    suite_version: int | None
    suite_sha256: str | None
    provenance: Any


def evaluations(db: DB, s: Submission, who: Viewer) -> list[Evaluation]:
    """The submission and its evaluations on other board versions that `who` may see, by
    version; empty when it has none."""
    others = [o for o in reevaluations_of(db, submission=s) if visible_to(db, o, who.user)]
    if not others:
        return []
    shown = sorted([s, *others], key=lambda o: (o.board_version, o.id))
    return [
        Evaluation(
            submission=o,
            this=o.id == s.id,
            suite_version=((o.result or {}).get("suite") or {}).get("version"),
            suite_sha256=((o.result or {}).get("suite") or {}).get("sha256"),
            provenance=provenance_of(o),
        )
        for o in shown
    ]


@dataclass(frozen=True)
class Episode:
    condition: str
    env_id: str
    row: EpisodeResultRow


def _episodes(db: DB, s: Submission, page: int) -> tuple[list[Episode], int]:
    rows, total = episode_rows(db, submission=s, page=page, per_page=EPISODES_PER_PAGE)
    return [Episode(condition=c, env_id=e, row=r) for r, c, e in rows], total


def outcome(
    db: DB, s: Submission, who: Viewer, episode_page: int = 1, *, store: VideoStore
) -> dict[str, Any]:
    """What the page shows below the live timeline: it changes when the submission ends."""
    private = owned_or_admin(s, who.user)
    rows = task_rows(db, submission=s)
    episodes, episode_total = _episodes(db, s, episode_page) if private else ([], 0)
    complete = all(r.complete for r in rows)
    chart_rows = [
        TaskSuccess(
            condition=r.condition,
            env_id=r.env_id,
            successes=r.successes,
            episodes=r.episodes,
            rate=r.success_rate,
            low=r.ci_low,
            high=r.ci_high,
        )
        for r in rows
        if r.success_rate is not None and r.ci_low is not None and r.ci_high is not None
    ]
    return {
        "submission": s,
        "private": private,
        "tasks": rows,
        "complete": complete,
        "episodes_ran": sum(r.episodes_ran for r in rows),
        "episodes_planned": sum(r.episodes for r in rows),
        "chart": success_bars(chart_rows) if rows and complete else None,
        "conditions": condition_means(rows),
        "provenance": provenance_of(s),
        "evaluations": evaluations(db, s, who),
        "attempts": attempts_of(db, submission=s) if private else None,
        "episodes": episodes,
        "episode_total": episode_total,
        "episode_page": episode_page,
        "episode_pages": max(1, -(-episode_total // EPISODES_PER_PAGE)),
        "show_seed": s.phase.public_seeds,
        "videos": videos_of(submission=s, store=store),
        "trajectories": trajectories_of(submission=s, store=store)
        if may_download_trajectories(s, who.user)
        else [],
        "ended_badly": s.state in ENDED_BADLY,
        "final": s.state.final,
        "may_mark_final": private and markable(s, now=utcnow()),
    }


@router.get("/submissions/{submission_id}")
def submission_page(
    submission_id: Id, request: Request, who: ViewerDep, db: DBDep, episodes: PageNo = 1
) -> Response:
    """The submission, its state timeline (kept live by /events) and, once ended, results."""
    s = get_visible(db, submission_id=submission_id, user=who.user)
    transitions = transitions_of(db, submission_id=s.id)
    return render(
        request,
        who,
        "submission.html",
        transitions=transitions,
        last_transition=transitions[-1].id if transitions else 0,
        queue=queue_out(db, submission=s, settings=services(request).settings),
        **outcome(db, s, who, episodes, store=video_store(services(request).settings)),
    )


@router.get("/submissions/{submission_id}/outcome")
def outcome_fragment(submission_id: Id, request: Request, who: ViewerDep, db: DBDep) -> Response:
    """The part of the page below the timeline, fetched by the page's script when it ends."""
    s = get_visible(db, submission_id=submission_id, user=who.user)
    store = video_store(services(request).settings)
    return render(request, who, "_outcome.html", **outcome(db, s, who, store=store))


# Actions ------------------------------------------------------------------------------------


Flag = Annotated[str, Form(pattern="^(true|false)$")]
Reason = Annotated[str, Form()]
"""Why an organizer acts (`server.audit.reason_of` says whether one is needed, and how long)."""


def _edit(
    request: Request,
    who: Viewer,
    db: DB,
    submission_id: int,
    *,
    admin: bool = False,
    public: bool | None = None,
    baseline: bool | None = None,
) -> Response:
    """An owner's (or, with `admin`, only an admin's) change of a flag, then back to the page."""
    user = admin_signed_in(request, who) if admin else signed_in(request, who)
    s = get_owned(db, submission_id=submission_id, user=user)
    edit(db, user=user, submission=s, public=public, baseline=baseline)
    db.commit()
    return redirect(f"/submissions/{s.id}")


@router.post("/submissions/{submission_id}/cancel")
def cancel_action(submission_id: Id, request: Request, who: PostedDep, db: DBDep) -> Response:
    user = signed_in(request, who)
    s = get_owned(db, submission_id=submission_id, user=user)
    cancel(db, user, s)
    db.commit()
    return redirect(f"/submissions/{s.id}")


@router.post("/submissions/{submission_id}/visibility")
def visibility_action(
    submission_id: Id, request: Request, who: PostedDep, db: DBDep, public: Flag
) -> Response:
    return _edit(request, who, db, submission_id, public=public == "true")


@router.post("/submissions/{submission_id}/rerun")
def rerun_action(
    submission_id: Id, request: Request, who: PostedDep, db: DBDep, reason: Reason = ""
) -> Response:
    admin = admin_signed_in(request, who)
    s = get_owned(db, submission_id=submission_id, user=admin)
    rerun(db, admin=admin, submission=s, reason=reason)
    db.commit()
    services(request).dispatcher.dispatch()
    return redirect(f"/submissions/{s.id}")


def _moderate(
    request: Request, who: Viewer, db: DB, submission_id: int, action: Moderation, reason: str
) -> Response:
    admin = admin_signed_in(request, who)
    s = get_owned(db, submission_id=submission_id, user=admin)
    moderate(db, by=admin, submission=s, action=action, reason=reason)
    db.commit()
    return redirect(f"/submissions/{s.id}")


@router.post("/submissions/{submission_id}/hidden")
def hidden_action(
    submission_id: Id,
    request: Request,
    who: PostedDep,
    db: DBDep,
    hidden: Flag,
    reason: Reason = "",
) -> Response:
    """An admin hides the submission (with a reason) or shows it again."""
    action: Moderation = "hide" if hidden == "true" else "unhide"
    return _moderate(request, who, db, submission_id, action, reason)


@router.post("/submissions/{submission_id}/disqualified")
def disqualified_action(
    submission_id: Id,
    request: Request,
    who: PostedDep,
    db: DBDep,
    disqualified: Flag,
    reason: Reason = "",
) -> Response:
    """An admin disqualifies the submission (with a reason) or reinstates it."""
    action: Moderation = "disqualify" if disqualified == "true" else "reinstate"
    return _moderate(request, who, db, submission_id, action, reason)


@router.post("/submissions/{submission_id}/baseline")
def baseline_action(
    submission_id: Id, request: Request, who: PostedDep, db: DBDep, baseline: Flag
) -> Response:
    return _edit(request, who, db, submission_id, admin=True, baseline=baseline == "true")


@router.post("/submissions/{submission_id}/final")
def final_action(
    submission_id: Id, request: Request, who: PostedDep, db: DBDep, final: Flag
) -> Response:
    """The owner marks the submission as their final choice in its phase, or takes it off."""
    user = signed_in(request, who)
    s = get_owned(db, submission_id=submission_id, user=user)
    mark_final(db, user=user, submission=s, final=final == "true")
    db.commit()
    return redirect(f"/submissions/{s.id}")


def _phase_action(
    request: Request, who: Viewer, db: DB, slug: str, phase: str, act: Any
) -> Response:
    admin = admin_signed_in(request, who)
    act(db, by=admin, slug=slug, phase=phase)
    db.commit()
    return redirect(f"/challenges/{slug}/leaderboard?{urlencode({'phase': phase})}")


@router.post("/challenges/{slug}/close")
def close_action(
    slug: str, request: Request, who: PostedDep, db: DBDep, phase: Annotated[str, Form()]
) -> Response:
    """An admin closes a phase now (docs/server.md, Challenge rules)."""
    return _phase_action(request, who, db, slug, phase, close_phase)


@router.post("/challenges/{slug}/publish")
def publish_action(
    slug: str, request: Request, who: PostedDep, db: DBDep, phase: Annotated[str, Form()]
) -> Response:
    """An admin publishes a phase's hidden board."""
    return _phase_action(request, who, db, slug, phase, publish_board)


@router.post("/challenges/{slug}/reevaluate")
def reevaluate_action(
    slug: str, request: Request, who: PostedDep, db: DBDep, phase: Annotated[str, Form()]
) -> Response:
    """An admin re-evaluates a phase's board into a new board version (docs/server.md)."""
    admin = admin_signed_in(request, who)
    challenge = get_challenge(db, slug=slug)
    target = shown_phase(challenge, name=phase)
    reevaluate(db, by=admin, challenge=challenge, phase=target)
    db.commit()
    services(request).dispatcher.dispatch()
    return redirect(f"/challenges/{challenge.slug}/leaderboard?{urlencode({'phase': target.name})}")
