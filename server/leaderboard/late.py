"""The post-deadline board of a phase whose rules take late submissions (`after_close:
post_deadline`): each participant's row among what they submitted after the close, by the
phase's `counts` rule. Read from the submissions, never from the official board's rows, so the
two never mix (docs/server.md, Challenge rules)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.challenges.service import get_challenge, get_phase
from server.kit.errors import NotFound
from server.models import Submission, User, team_of
from server.standings.entries import competing, participant_of, row_order, standing


@dataclass(frozen=True)
class LateRow:
    rank: int | None  # None where a hidden board shows a participant only their own rows
    username: str
    submission_id: int
    score: float
    submitted_at: datetime


def post_deadline_board(db: DB, *, slug: str, phase: str, viewer: User | None) -> list[LateRow]:
    """The phase's post-deadline board as `viewer` may see it (a hidden board: organizers all,
    each participant their own row)."""
    challenge = get_challenge(db, slug=slug)
    found = get_phase(challenge, phase)
    if found.after_close != "post_deadline":
        raise NotFound(f"phase {phase!r} of {slug!r} takes no submissions after it closes")
    late = db.execute(
        select(Submission, User.username)
        .join(User, User.id == Submission.user_id)
        .where(
            *standing(found.id, found.board_version),
            Submission.post_deadline.is_(True),
            *competing(),  # baselines and disqualified submissions are not on it
        )
        .order_by(*row_order(counts=found.counts, final_choice=False))
    ).all()
    rows: dict[str, tuple[Submission, str]] = {}
    for submission, username in late:
        owner = participant_of(submission, team_mode=challenge.team_mode)
        rows.setdefault(owner, (submission, username))
    ranked = sorted(rows.values(), key=lambda r: (-(r[0].score or 0.0), r[0].created_at, r[0].id))
    whole = found.board_shown_to_all() or (viewer is not None and viewer.is_admin)
    if whole:
        return [_row(i + 1, *r) for i, r in enumerate(ranked)]
    mine = _owners_of(db, viewer, team_mode=challenge.team_mode)
    return [
        _row(None, *r)
        for r in ranked
        if participant_of(r[0], team_mode=challenge.team_mode) in mine
    ]


def _owners_of(db: DB, viewer: User | None, *, team_mode: bool) -> set[str]:
    if viewer is None:
        return set()
    team = team_of(db, user_id=viewer.id) if team_mode else None
    return {f"user:{viewer.id}"} | ({f"team:{team.id}"} if team is not None else set())


def _row(rank: int | None, submission: Submission, username: str) -> LateRow:
    assert submission.score is not None
    return LateRow(
        rank=rank,
        username=username,
        submission_id=submission.id,
        score=submission.score,
        submitted_at=submission.created_at,
    )
