"""The submissions API, ``/api/v1/submissions``: submit, follow, read results, cancel,
re-run and edit."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from server.accounts.deps import CallerDep, UserDep, require_admin
from server.challenges.service import get_challenge, get_phase
from server.challenges.tracks import get_track
from server.kit.deps import DBDep, Id, PageNo, PerPage, limit
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import SLUG_PATTERN, Page
from server.models import Submission
from server.submissions.deps import services
from server.submissions.final import mark_final
from server.submissions.method import Method
from server.submissions.moderation import rerun
from server.submissions.position import queue_out
from server.submissions.schemas import (
    EpisodeOut,
    LogsOut,
    ReasonIn,
    SubmissionDetail,
    SubmissionOut,
    SubmissionPatch,
    SubmitIn,
    TaskResultOut,
    TransitionOut,
)
from server.submissions.service import (
    cancel,
    condition_means,
    edit,
    episode_rows,
    get_owned,
    get_visible,
    list_submissions,
    provenance_of,
    submit,
    task_rows,
    transitions_of,
)

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)


def submission_out(s: Submission) -> SubmissionOut:
    """A submission as the API shows it."""
    return SubmissionOut(
        id=s.id,
        username=s.user.username,
        challenge=s.challenge.slug,
        phase=s.phase.name,
        image=s.image,
        pinned_image=s.pinned_image,
        description=s.description,
        method=s.method,
        paper_url=s.paper_url,
        code_url=s.code_url,
        public=s.public,
        hidden=s.hidden,
        disqualified=s.disqualified,
        moderation_reason=s.moderation_reason,
        baseline=s.baseline,
        state=s.state,
        reason=s.reason,
        attempt=s.attempt,
        created_at=s.created_at,
        started_at=s.started_at,
        finished_at=s.finished_at,
        score=s.score,
        progress=s.progress,
        final=s.final_for is not None,
        post_deadline=s.post_deadline,
    )


@router.post("/submissions", status_code=202, tags=["submissions"])
def create_submission(body: SubmitIn, request: Request, user: UserDep, db: DBDep) -> SubmissionOut:
    """Submit an image: its tag is resolved and pinned to a digest now; the evaluation is queued."""
    limit(request, "submit", user=user)
    svc = services(request)
    challenge = get_track(db, get_challenge(db, slug=body.challenge), body.track)
    submission = submit(
        db,
        user=user,
        challenge=challenge,
        phase=get_phase(challenge, body.phase),
        image=body.image,
        description=body.description,
        public=body.public,
        method=Method(name=body.method, paper_url=body.paper_url, code_url=body.code_url),
        resolve=svc.resolve,
        require_verified_email=svc.settings.email_verification_required,
        policy_gpus=svc.settings.policy_gpus,
    )
    db.commit()
    svc.dispatcher.dispatch()  # after the commit; the periodic sweep retries if this fails
    return submission_out(submission)


@router.get("/submissions", tags=["submissions"])
def my_submissions(
    user: UserDep,
    db: DBDep,
    challenge: Annotated[str | None, Query(max_length=64, pattern=SLUG_PATTERN)] = None,
    page: PageNo = 1,
    per_page: PerPage = 50,
) -> Page[SubmissionOut]:
    """Your submissions, newest first."""
    rows, total = list_submissions(
        db,
        user=user,
        challenge=get_challenge(db, slug=challenge) if challenge is not None else None,
        page=page,
        per_page=per_page,
    )
    return Page(items=[submission_out(s) for s in rows], page=page, per_page=per_page, total=total)


@router.get("/submissions/{submission_id}", tags=["submissions"])
def submission_detail(
    submission_id: Id, request: Request, who: CallerDep, db: DBDep
) -> SubmissionDetail:
    s = get_visible(db, submission_id=submission_id, user=who.user)
    transitions = transitions_of(db, submission_id=s.id)
    rows = task_rows(db, submission=s)
    return SubmissionDetail(
        **submission_out(s).model_dump(exclude={"queue"}),
        queue=queue_out(db, submission=s, settings=services(request).settings),
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
        tasks=[TaskResultOut.model_validate(r, from_attributes=True) for r in rows],
        conditions=condition_means(rows),
        provenance=provenance_of(s),
    )


@router.get("/submissions/{submission_id}/episodes", tags=["submissions"])
def submission_episodes(
    submission_id: Id,
    who: CallerDep,
    db: DBDep,
    page: PageNo = 1,
    per_page: Annotated[int, Query(ge=1, le=1000)] = 200,
) -> Page[EpisodeOut]:
    """Per-episode records (owner and admins; others who may see the submission get 403).
    Seeds of secret-seed phases are never shown."""
    s = get_owned(db, submission_id=submission_id, user=who.user, part="episodes")
    rows, total = episode_rows(db, submission=s, page=page, per_page=per_page)
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
    """The tail of the policy's stdout/stderr (owner and admins; others who may see the
    submission get 403)."""
    s = get_owned(db, submission_id=submission_id, user=who.user, part="logs")
    return LogsOut(submission_id=s.id, attempt=s.attempt, log_tail=s.log_tail)


@router.post("/submissions/{submission_id}/cancel", tags=["submissions"])
def cancel_submission(submission_id: Id, user: UserDep, db: DBDep) -> SubmissionOut:
    s = get_owned(db, submission_id=submission_id, user=user)
    cancel(db, user, s)
    db.commit()
    return submission_out(s)


@router.put("/submissions/{submission_id}/final", tags=["submissions"])
def mark_submission_final(submission_id: Id, user: UserDep, db: DBDep) -> SubmissionOut:
    """Make it your final choice in its phase (where the phase gives one): the mark moves
    from the submission that had it."""
    s = get_owned(db, submission_id=submission_id, user=user)
    mark_final(db, user=user, submission=s, final=True)
    db.commit()
    return submission_out(s)


@router.delete("/submissions/{submission_id}/final", tags=["submissions"])
def unmark_submission_final(submission_id: Id, user: UserDep, db: DBDep) -> SubmissionOut:
    """Take your final mark off it: the phase's `counts` rule picks your row again."""
    s = get_owned(db, submission_id=submission_id, user=user)
    mark_final(db, user=user, submission=s, final=False)
    db.commit()
    return submission_out(s)


@router.post("/submissions/{submission_id}/rerun", tags=["admin"])
def rerun_submission(
    submission_id: Id,
    request: Request,
    user: UserDep,
    db: DBDep,
    body: ReasonIn | None = None,
) -> SubmissionOut:
    """Run an ended submission again as a new attempt (admins; a reason is optional)."""
    admin = require_admin(user)  # after the body's checks, as every route's
    s = get_owned(db, submission_id=submission_id, user=admin)
    rerun(db, admin=admin, submission=s, reason=body.reason if body is not None else None)
    db.commit()
    services(request).dispatcher.dispatch()
    return submission_out(s)


@router.patch("/submissions/{submission_id}", tags=["submissions"])
def update_submission(
    submission_id: Id, body: SubmissionPatch, user: UserDep, db: DBDep
) -> SubmissionOut:
    """Owners change visibility, description and method; admins also hide and flag baselines."""
    s = get_owned(db, submission_id=submission_id, user=user)
    edit(
        db,
        user=user,
        submission=s,
        public=body.public,
        hidden=body.hidden,
        baseline=body.baseline,
        reason=body.reason,
        description=body.description,
        method=Method(name=body.method, paper_url=body.paper_url, code_url=body.code_url),
    )
    db.commit()
    return submission_out(s)
