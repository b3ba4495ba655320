"""Re-evaluation: every entry of a phase's board run again, on the challenge's current suite
and evaluator, into a new board version (docs/server.md, Re-evaluation).

Each entry's submission gets a copy that counts for the new version (`reevaluation_of`), queued
through the outbox as any submission is: the workers, executors and state machine run it
unchanged. The copies hold no quota (`server.challenges.quota`); the version is published by
`server.standings.versions` once they have ended.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server import audit
from server.kit.errors import Conflict
from server.models import (
    Challenge,
    LeaderboardEntry,
    Phase,
    State,
    Submission,
    User,
    utcnow,
)
from server.submissions.changes import changed
from server.submissions.moderation import check_organizer
from server.submissions.states import queued_first

COPIED = (
    "user_id",
    "challenge_id",
    "phase_id",
    "team_id",
    "image",
    "pinned_image",
    "image_bytes",
    "description",
    "method",
    "paper_url",
    "code_url",
    "public",
    "hidden",
    "disqualified",
    "moderation_reason",
    "baseline",
    "created_at",
    "post_deadline",
)
"""What a re-evaluation keeps of its original: whose it is, what runs, how it is shown, and when
it was submitted (the board's "submitted" and its tie-break stay the participant's), and
whether it came late. Its final mark stays on the original, and counts for its re-evaluations."""


class NothingToReevaluate(Conflict):
    """The phase's board has no entries."""


@dataclass(frozen=True)
class Started:
    """A phase's re-evaluation, queued."""

    phase: str
    board_version: int
    submissions: list[int]
    """The re-evaluations' ids, in the board's order."""


def reevaluate(
    db: DB,
    *,
    by: User | None,
    challenge: Challenge,
    phase: Phase,
    now: datetime | None = None,
) -> Started:
    """Queue a re-evaluation of every entry of the phase's current board into the next board
    version (an organizer's action: `by` an admin, or None for the command line; recorded
    with each copy and in the audit log)."""
    check_organizer(by)
    who = f"admin {by.username}" if by is not None else "the operator"
    now = now or utcnow()
    # One re-evaluation at a time: the phase's row is the lock.
    db.refresh(phase, with_for_update=True)
    if phase.pending_board_version is not None:
        raise Conflict(
            f"phase {phase.name!r} of {challenge.slug!r} is being re-evaluated already "
            f"(into board version {phase.pending_board_version})"
        )
    entries = db.scalars(
        select(LeaderboardEntry.submission_id)
        .where(
            LeaderboardEntry.phase_id == phase.id,
            LeaderboardEntry.board_version == phase.board_version,
        )
        .order_by(LeaderboardEntry.score.desc(), LeaderboardEntry.submitted_at)
    ).all()
    if not entries:
        raise NothingToReevaluate(
            f"phase {phase.name!r} of {challenge.slug!r} has no entries on its board to re-evaluate"
        )
    version = phase.board_version + 1
    phase.pending_board_version = version
    originals = {
        s.id: s for s in db.scalars(select(Submission).where(Submission.id.in_(entries))).all()
    }
    copies = [
        _copy(db, originals[sid], version=version, by=who, now=now)
        for sid in entries
        if sid in originals
    ]
    audit.record(
        db,
        by=by,
        action="phase.reevaluate",
        target_kind="phase",
        target_id=phase.id,
        challenge_id=challenge.id,
        detail={"phase": phase.name, "board_version": version, "submissions": copies},
    )
    db.flush()
    return Started(phase=phase.name, board_version=version, submissions=copies)


def _copy(db: DB, original: Submission, *, version: int, by: str, now: datetime) -> int:
    copy = Submission(
        **{name: getattr(original, name) for name in COPIED},
        reevaluation_of=original.reevaluation_of or original.id,  # the participant's own
        board_version=version,
        state=State.QUEUED,
        reason="waiting for a worker",
        attempt=1,
        updated_at=now,
    )
    db.add(copy)
    db.flush()
    reason = f"re-evaluation of submission {original.id} for board version {version}, by {by}"
    queued_first(db, copy, reason, now=now)
    changed(db, copy.id)
    return copy.id


def reevaluations_of(db: DB, *, submission: Submission) -> list[Submission]:
    """The evaluations of the same entry on other board versions: the original of a
    re-evaluation and its other re-evaluations, or an original's re-evaluations; by version."""
    root = submission.reevaluation_of or submission.id
    found = db.scalars(
        select(Submission)
        .where(
            (Submission.id == root) | (Submission.reevaluation_of == root),
            Submission.id != submission.id,
        )
        .order_by(Submission.board_version, Submission.id)
    ).all()
    return list(found)
