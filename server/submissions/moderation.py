"""An organizer's actions on submissions: hide, disqualify (and undo either), flag a baseline,
re-run one, re-run the stuck. Each is recorded in the audit log in the transaction that makes
it (docs/server.md, Organizer tools); `by` is the admin, or None for the command line.

Hiding takes a submission off every board; disqualifying keeps it on its board, unranked, with
the reason. Which submissions stand on a board, and how, is decided in
`server.standings.entries` (`standing`, `competing`): here only the flags change and the
owner's rows are recomputed.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server import audit
from server.kit.errors import Conflict, Forbidden
from server.models import Challenge, State, Submission, User, utcnow
from server.standings.entries import refresh
from server.standings.versions import publish_when_done
from server.submissions.changes import changed
from server.submissions.reconcile import Timeouts, stuck
from server.submissions.states import new_attempt, transition

Moderation = Literal["hide", "unhide", "disqualify", "reinstate"]

_FLAGS: dict[str, tuple[str, bool]] = {
    "hide": ("hidden", True),
    "unhide": ("hidden", False),
    "disqualify": ("disqualified", True),
    "reinstate": ("disqualified", False),
}
"""Each action's flag and the value it sets. Setting one needs a reason, which its owner is
shown; clearing one takes an optional reason, kept in the audit log."""


def check_organizer(by: User | None) -> None:
    """Forbidden unless `by` is an admin (None: the command line on the server's host)."""
    if by is not None and not by.is_admin:
        raise Forbidden("admins only")


def moderate(
    db: DB, *, by: User | None, submission: Submission, action: Moderation, reason: str | None
) -> Submission:
    """Hide, unhide, disqualify or reinstate a submission: its owner's boards are recomputed
    and the action recorded. Hiding or disqualifying again replaces the reason."""
    check_organizer(by)
    flag, value = _FLAGS[action]
    why = audit.reason_of(reason, required=value)
    if not value and not getattr(submission, flag):
        raise Conflict(f"submission {submission.id} is not {flag}")
    setattr(submission, flag, value)
    if value:
        submission.moderation_reason = why
    elif not (submission.hidden or submission.disqualified):
        submission.moderation_reason = None  # else the other flag's reason stands
    db.flush()
    changed(db, submission.id)  # open views check again who may see it
    refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    if action == "hide":  # a re-evaluation hidden after an error holds its version no longer
        publish_when_done(db, phase_id=submission.phase_id)
    _record(db, by, submission, f"submission.{action}", why)
    return submission


def flag_baseline(db: DB, *, by: User | None, submission: Submission, baseline: bool) -> None:
    """Flag a submission as a baseline (an unranked row of its own) or take the flag off."""
    check_organizer(by)
    if submission.baseline == baseline:
        return
    submission.baseline = baseline
    db.flush()
    changed(db, submission.id)
    refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    _record(db, by, submission, "submission.baseline", "", {"baseline": baseline})


def rerun(
    db: DB,
    *,
    admin: User | None,
    submission: Submission,
    reason: str | None = None,
    now: datetime | None = None,
) -> None:
    """Run an ended submission again, as a new attempt with its own results."""
    check_organizer(admin)
    why = audit.reason_of(reason, required=False)
    said = f"re-run by an admin: {why}" if why else "re-run by an admin"
    if not new_attempt(db, submission, said, now=now):
        raise Conflict(f"submission {submission.id} has not ended; cancel it first")
    detail = {"attempt": submission.attempt}
    _record(db, admin, submission, "submission.rerun", why, detail)


def rerun_stuck(
    db: DB,
    *,
    by: User | None,
    challenge: Challenge | None,
    timeouts: Timeouts,
    reason: str | None = None,
    now: datetime | None = None,
) -> list[int]:
    """End every stuck attempt (`server.submissions.reconcile.stuck`) of the challenge (None:
    of all) as `error` and queue it again as a new attempt, now rather than at the
    reconciler's next pass, and whatever it lost before; the ids queued, in id order."""
    check_organizer(by)
    why = audit.reason_of(reason, required=False)
    now = now or utcnow()
    query = select(Submission).where(stuck(timeouts, now)).order_by(Submission.id)
    if challenge is not None:
        query = query.where(Submission.challenge_id == challenge.id)
    queued: list[int] = []
    for s in db.scalars(query).all():
        ended = "stuck: ended by an organizer to run it again"
        if not transition(db, s.id, s.attempt, State.ERROR, ended, now=now):
            continue  # it moved on meanwhile (a late report)
        db.refresh(s)
        again = "stuck before: run again by an organizer"
        if new_attempt(db, s, again, from_states=frozenset({State.ERROR}), now=now):
            queued.append(s.id)
    if queued:
        audit.record(
            db,
            by=by,
            action="challenge.rerun_stuck",
            target_kind="challenge",
            target_id=challenge.id if challenge is not None else None,
            challenge_id=challenge.id if challenge is not None else None,
            reason=why,
            detail={"submissions": queued},
        )
        db.flush()
    return queued


def _record(
    db: DB,
    by: User | None,
    submission: Submission,
    action: str,
    reason: str,
    detail: dict[str, Any] | None = None,
) -> None:
    audit.record(
        db,
        by=by,
        action=action,
        target_kind="submission",
        target_id=submission.id,
        challenge_id=submission.challenge_id,
        reason=reason,
        detail=detail,
    )
    db.flush()
