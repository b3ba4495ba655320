"""A participant's final choice in a phase whose rules give one (`Phase.final_choice`): the
submission that stands on the board once it succeeded, whatever `counts` says
(docs/server.md, Challenge rules)."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import select, update
from sqlalchemy.orm import Session as DB

from server.challenges.service import lock_phase
from server.kit.errors import Conflict, Invalid, NotFound
from server.models import Challenge, Submission, Team, User, utcnow
from server.standings.entries import participant_of, refresh
from server.submissions.changes import changed
from server.submissions.service import owned_or_admin


def markable(submission: Submission, *, now: datetime) -> bool:
    """Whether the page offers a final mark on it (`mark_final` checks again, under locks):
    its phase gives a final choice and is open, and it is a participant's own, on time."""
    phase = submission.phase
    return (
        phase.final_choice
        and phase.is_open(now)
        and not submission.post_deadline
        and submission.reevaluation_of is None
    )


def mark_final(
    db: DB, *, user: User, submission: Submission, final: bool, now: datetime | None = None
) -> None:
    """Make the submission its owner's (or team's) final choice in its phase, moving the mark
    from the one that had it, or (`final` False) take its mark off; the board follows."""
    if not owned_or_admin(submission, user):
        raise NotFound(f"no submission {submission.id}")
    if submission.reevaluation_of is not None:
        raise Invalid(
            f"submission {submission.id} re-evaluates {submission.reevaluation_of}: "
            "mark that one, the mark counts for its re-evaluations"
        )
    if submission.post_deadline:
        raise Conflict(f"submission {submission.id} came after the deadline: it cannot be final")
    challenge = db.get(Challenge, submission.challenge_id)
    if challenge is None:
        raise NotFound(f"no submission {submission.id}")  # its challenge went meanwhile
    _lock_owner(db, submission=submission, challenge=challenge)
    # A close is wholly before or after this; the refresh below updates the row anyway.
    phase = lock_phase(db, phase_id=submission.phase_id, write=True)
    where = f"phase {phase.name!r} of {challenge.slug!r}"
    if not phase.final_choice:
        raise Conflict(f"{where} takes no final choice: its board shows the {phase.counts} one")
    now = now or utcnow()
    if phase.closes_at is not None and phase.closes_at <= now:
        raise Conflict(f"{where} closed at {phase.closes_at:%Y-%m-%d %H:%M} UTC: choices stand")
    owner = participant_of(submission, team_mode=challenge.team_mode)
    db.execute(
        update(Submission)
        .where(Submission.phase_id == phase.id, Submission.final_for == owner)
        .values(final_for=None)
        .execution_options(synchronize_session="fetch")
    )
    if final:
        db.flush()  # the old mark is gone before the new one meets the unique index
        submission.final_for = owner
    db.flush()
    changed(db, submission.id)
    refresh(db, phase_id=phase.id, user_id=submission.user_id)


def _lock_owner(db: DB, *, submission: Submission, challenge: Challenge) -> None:
    # The entries' lock order: the user, then their team. Two marks by one participant (or
    # two members of a team) take turns; the unique index holds if anything else does not.
    db.execute(select(User.id).where(User.id == submission.user_id).with_for_update(key_share=True))
    if challenge.team_mode and submission.team_id is not None:
        db.execute(
            select(Team.id).where(Team.id == submission.team_id).with_for_update(key_share=True)
        )
