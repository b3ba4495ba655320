"""The public API's submissions, ``/api/v1/submissions``: submit, follow, read results, cancel,
re-run and edit."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from sqlalchemy import func, select

from server.challenges import get_challenge, get_phase
from server.deps import (
    AdminDep,
    CallerDep,
    DBDep,
    Id,
    PageNo,
    PerPage,
    UserDep,
    limit,
    services,
)
from server.errors import ERROR_RESPONSES, NotFound
from server.ingest import condition_means, episode_rows, task_rows
from server.models import (
    Submission,
    Transition,
    User,
)
from server.schemas import (
    EpisodeOut,
    LogsOut,
    Page,
    SubmissionDetail,
    SubmissionOut,
    SubmissionPatch,
    SubmitIn,
    TaskResultOut,
    TransitionOut,
)
from server.submissions import (
    cancel,
    edit,
    get_visible,
    owned_or_admin,
    rerun,
    submit,
)

router = APIRouter(responses=ERROR_RESPONSES)


def _submission_out(s: Submission) -> SubmissionOut:
    return SubmissionOut(
        id=s.id,
        username=s.user.username,
        challenge=s.challenge.slug,
        phase=s.phase.name,
        image=s.image,
        pinned_image=s.pinned_image,
        description=s.description,
        public=s.public,
        hidden=s.hidden,
        baseline=s.baseline,
        state=s.state,
        reason=s.reason,
        attempt=s.attempt,
        created_at=s.created_at,
        started_at=s.started_at,
        finished_at=s.finished_at,
        score=s.score,
        progress=s.progress,
    )


@router.post("/submissions", status_code=202, tags=["submissions"])
def create_submission(body: SubmitIn, request: Request, user: UserDep, db: DBDep) -> SubmissionOut:
    """Submit an image: its tag is resolved and pinned to a digest now; the evaluation is queued."""
    limit(request, "submit", user=user)
    svc = services(request)
    challenge = get_challenge(db, body.challenge)
    phase = get_phase(challenge, body.phase)
    submission = submit(
        db,
        user,
        challenge,
        phase,
        image=body.image,
        description=body.description,
        public=body.public,
        resolve=svc.resolve,
    )
    db.commit()
    svc.dispatcher.dispatch()  # after the commit; the periodic sweep retries if this fails
    return _submission_out(submission)


@router.get("/submissions", tags=["submissions"])
def my_submissions(
    user: UserDep,
    db: DBDep,
    challenge: Annotated[str | None, Query(max_length=64)] = None,
    page: PageNo = 1,
    per_page: PerPage = 50,
) -> Page[SubmissionOut]:
    """Your submissions, newest first."""
    query = select(Submission).where(Submission.user_id == user.id)
    if challenge is not None:
        query = query.where(Submission.challenge_id == get_challenge(db, challenge).id)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.scalars(
        query.order_by(Submission.created_at.desc(), Submission.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    )
    return Page(items=[_submission_out(s) for s in rows], page=page, per_page=per_page, total=total)


@router.get("/submissions/{submission_id}", tags=["submissions"])
def submission_detail(submission_id: Id, who: CallerDep, db: DBDep) -> SubmissionDetail:
    s = get_visible(db, submission_id, who.user)
    transitions = db.scalars(
        select(Transition).where(Transition.submission_id == s.id).order_by(Transition.id)
    )
    rows = task_rows(db, s)
    return SubmissionDetail(
        **_submission_out(s).model_dump(),
        transitions=[
            TransitionOut(
                attempt=t.attempt,
                from_state=t.from_state,
                to_state=t.to_state,
                reason=t.reason,
                at=t.at,
            )
            for t in transitions
        ],
        tasks=[
            TaskResultOut(
                condition=r.condition,
                env_id=r.env_id,
                episodes=r.episodes,
                successes=r.successes,
                success_rate=r.success_rate,
                ci_low=r.ci_low,
                ci_high=r.ci_high,
                mean_steps=r.mean_steps,
            )
            for r in rows
        ],
        conditions=condition_means(rows),
    )


def _owned(db: DBDep, submission_id: Id, user: User | None) -> Submission:
    s = db.get(Submission, submission_id)
    if s is None or not owned_or_admin(s, user):
        raise NotFound(f"no submission {submission_id}")
    return s


@router.get("/submissions/{submission_id}/episodes", tags=["submissions"])
def submission_episodes(
    submission_id: Id,
    who: CallerDep,
    db: DBDep,
    page: PageNo = 1,
    per_page: Annotated[int, Query(ge=1, le=1000)] = 200,
) -> Page[EpisodeOut]:
    """Per-episode records (owner and admins). Seeds of secret-seed phases are never shown."""
    s = _owned(db, submission_id, who.user)
    rows, total = episode_rows(db, s, page=page, per_page=per_page)
    show_seed = s.phase.public_seeds
    items = [
        EpisodeOut(
            condition=condition,
            env_id=env_id,
            index=e.index,
            seed=e.seed if show_seed else None,
            success_once=e.success_once,
            success_at_end=e.success_at_end,
            steps=e.steps,
            episode_return=e.episode_return,
            wall_time_s=e.wall_time_s,
            invalid_actions=e.invalid_actions,
            clipped_actions=e.clipped_actions,
            failure=e.failure,
        )
        for e, condition, env_id in rows
    ]
    return Page(items=items, page=page, per_page=per_page, total=total)


@router.get("/submissions/{submission_id}/logs", tags=["submissions"])
def submission_logs(submission_id: Id, who: CallerDep, db: DBDep) -> LogsOut:
    """The tail of the policy's stdout/stderr (owner and admins)."""
    s = _owned(db, submission_id, who.user)
    return LogsOut(submission_id=s.id, attempt=s.attempt, log_tail=s.log_tail)


@router.post("/submissions/{submission_id}/cancel", tags=["submissions"])
def cancel_submission(submission_id: Id, user: UserDep, db: DBDep) -> SubmissionOut:
    s = _owned(db, submission_id, user)
    cancel(db, user, s)
    db.commit()
    return _submission_out(s)


@router.post("/submissions/{submission_id}/rerun", tags=["admin"])
def rerun_submission(
    submission_id: Id, request: Request, admin: AdminDep, db: DBDep
) -> SubmissionOut:
    """Run an ended submission again as a new attempt (admins)."""
    s = _owned(db, submission_id, admin)
    rerun(db, admin, s)
    db.commit()
    services(request).dispatcher.dispatch()
    return _submission_out(s)


@router.patch("/submissions/{submission_id}", tags=["submissions"])
def update_submission(
    submission_id: Id, body: SubmissionPatch, user: UserDep, db: DBDep
) -> SubmissionOut:
    """Owners change visibility and description; admins also hide and flag baselines."""
    s = _owned(db, submission_id, user)
    edit(
        db,
        user,
        s,
        public=body.public,
        hidden=body.hidden,
        baseline=body.baseline,
        description=body.description,
    )
    db.commit()
    return _submission_out(s)
