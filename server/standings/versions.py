"""Board versions: a re-evaluation in progress is published as the phase's board once every
re-evaluation of it has ended and none waits on the service (docs/server.md, Re-evaluation)."""

from __future__ import annotations

from sqlalchemy import ColumnElement, select, update
from sqlalchemy.orm import Session as DB

from server.models import ACTIVE_STATES, Phase, State, Submission
from server.standings.entries import moved, refresh


def holding(phase_id: int, board_version: int) -> tuple[ColumnElement[bool], ...]:
    """Conditions on a re-evaluation that holds the publication of `board_version`: it still
    runs, or it ended in the service's error and nobody has re-run or hidden it."""
    return (
        Submission.phase_id == phase_id,
        Submission.board_version == board_version,
        Submission.reevaluation_of.is_not(None),
        Submission.state.in_(ACTIVE_STATES)
        | ((Submission.state == State.ERROR) & Submission.hidden.is_(False)),
    )


def publish_when_done(db: DB, *, phase_id: int) -> bool:
    """Publish the phase's pending board version if nothing holds it; whether it did."""
    pending = db.scalar(
        select(Phase.pending_board_version).where(Phase.id == phase_id).with_for_update()
    )
    if pending is None:
        return False
    if db.scalar(select(Submission.id).where(*holding(phase_id, pending)).limit(1)):
        return False
    db.execute(
        update(Phase)
        .where(Phase.id == phase_id)
        .values(board_version=pending, pending_board_version=None)
        .execution_options(synchronize_session=False)
    )
    moved(db, phase_id)  # readers of the current board read the new version
    db.flush()
    return True


def published_after_end(db: DB, *, submission_id: int) -> None:
    """A submission ended (or was hidden): if it is a re-evaluation, its owner's rows are
    recomputed and its version published when due. The rows first: that takes the locks in
    `server.standings.entries`' order (user, teams, phase), the publication's phase last."""
    submission = db.get(Submission, submission_id)
    if submission is None or submission.reevaluation_of is None:
        return
    db.refresh(submission)  # the state machine's updates bypass the session
    refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    publish_when_done(db, phase_id=submission.phase_id)
