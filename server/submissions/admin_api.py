"""The organizer's API (admins only): hide, disqualify and undo either; re-run the stuck;
re-evaluate a phase; export a challenge's submissions; read the audit log (docs/server.md,
Organizer tools)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse

from server.accounts.deps import AdminDep, UserDep, require_admin
from server.challenges.service import get_challenge, get_phase, shown_phase
from server.kit.deps import DBDep, Id
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import SLUG_PATTERN
from server.submissions.api import submission_out
from server.submissions.audit_log import audit_listing
from server.submissions.deps import services
from server.submissions.export import export_text
from server.submissions.moderation import Moderation, moderate, rerun_stuck
from server.submissions.reconcile import timeouts_of
from server.submissions.reevaluation import reevaluate
from server.submissions.schemas import (
    AuditPage,
    AuditRecordOut,
    ReasonIn,
    ReevaluationOut,
    RerunStuckIn,
    RerunStuckOut,
    SubmissionOut,
)
from server.submissions.service import get_owned

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES, tags=["admin"])

Slug = Annotated[str, Query(max_length=64, pattern=SLUG_PATTERN)]
_MEDIA = {"csv": "text/csv; charset=utf-8", "json": "application/json"}
_SAID = {
    "hide": "Take it off every board (a reason is required; its owner is shown it).",
    "unhide": "Put a hidden submission back on its board (a reason is optional).",
    "disqualify": "Keep it on its board, unranked after the ranked rows, marked disqualified "
    "with the reason (required).",
    "reinstate": "Rank a disqualified submission again (a reason is optional).",
}


def _moderation(action: Moderation) -> Callable[..., SubmissionOut]:
    def act(submission_id: Id, body: ReasonIn, user: UserDep, db: DBDep) -> SubmissionOut:
        admin = require_admin(user)  # after the body's checks: a bad body is a 422 to anyone
        s = get_owned(db, submission_id=submission_id, user=admin)
        moderate(db, by=admin, submission=s, action=action, reason=body.reason)
        db.commit()
        return submission_out(s)

    act.__doc__ = _SAID[action]
    act.__name__ = f"{action}_submission"
    return act


_ACTIONS: tuple[Moderation, ...] = ("hide", "unhide", "disqualify", "reinstate")
for _action in _ACTIONS:
    router.post(f"/submissions/{{submission_id}}/{_action}")(_moderation(_action))


@router.post("/admin/rerun-stuck")
def rerun_stuck_submissions(
    body: RerunStuckIn, request: Request, user: UserDep, db: DBDep
) -> RerunStuckOut:
    """End every stuck attempt (past its deadline, or silent past the heartbeat timeout) of a
    challenge, or of all, and queue it again as a new attempt, now."""
    admin = require_admin(user)
    svc = services(request)
    challenge = get_challenge(db, slug=body.challenge) if body.challenge is not None else None
    requeued = rerun_stuck(
        db,
        by=admin,
        challenge=challenge,
        timeouts=timeouts_of(svc.settings),
        reason=body.reason,
    )
    db.commit()
    svc.dispatcher.dispatch()
    return RerunStuckOut(requeued=requeued)


@router.post("/challenges/{slug}/phases/{phase}/reevaluate")
def reevaluate_phase(
    slug: str, phase: str, request: Request, admin: AdminDep, db: DBDep
) -> ReevaluationOut:
    """Run every entry of the phase's board again, on the current suite and evaluator, into a
    new board version (docs/server.md, Re-evaluation)."""
    challenge = get_challenge(db, slug=slug)
    target = shown_phase(challenge, name=phase)
    started = reevaluate(db, by=admin, challenge=challenge, phase=target)
    db.commit()
    services(request).dispatcher.dispatch()
    return ReevaluationOut(
        phase=started.phase, board_version=started.board_version, submissions=started.submissions
    )


@router.get(
    "/admin/challenges/{slug}/export",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/csv": {}, "application/json": {}}}},
)
def export_submissions(
    slug: str,
    admin: AdminDep,
    db: DBDep,
    format: Literal["csv", "json"] = "csv",
    phase: Annotated[str | None, Query(max_length=32)] = None,
) -> StreamingResponse:
    """Every submission of the challenge (of one phase) with its result, one row each: id,
    user, team, phase, state, reason and error cause, attempt, score, each condition's mean,
    hidden, disqualified and why, times, pinned image. Streamed as it is read."""
    challenge = get_challenge(db, slug=slug)
    only = get_phase(challenge, phase) if phase is not None else None
    name = f"{challenge.slug}{'-' + only.name if only else ''}-submissions.{format}"
    return StreamingResponse(
        export_text(db, challenge=challenge, phase=only, format=format),
        media_type=_MEDIA[format],
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )


@router.get("/admin/audit")
def audit_records(
    admin: AdminDep,
    db: DBDep,
    challenge: Slug | None = None,
    action: Annotated[str | None, Query(max_length=64)] = None,
    before_id: Annotated[int | None, Query(ge=1)] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
) -> AuditPage:
    """The organizers' actions, newest first: filter by challenge and action; page with
    `before_id` (the last page's `next_before_id`)."""
    listing = audit_listing(
        db, challenge=challenge, action=action, before_id=before_id, limit=limit
    )
    items = [
        AuditRecordOut(
            id=e.record.id,
            at=e.record.at,
            actor=e.record.actor,
            action=e.record.action,
            target_kind=e.record.target_kind,
            target_id=e.record.target_id,
            challenge=e.challenge,
            reason=e.record.reason,
            detail=e.record.detail,
        )
        for e in listing.entries
    ]
    return AuditPage(items=items, next_before_id=listing.next_before_id)
