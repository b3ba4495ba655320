"""Disabling an account, whole: the account is refused from then on (server/accounts/service.py)
and its unfinished submissions are cancelled, in one transaction. The cancel is the state
machine's, from this floor: accounts sit below submissions."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.accounts import service as accounts
from server.models import ACTIVE_STATES, State, Submission, User, utcnow
from server.submissions.states import transition

CANCEL_REASON = "cancelled: an administrator disabled the account"


def disable_account(
    db: DB, *, user: User, by: User | None, reason: str | None, now: datetime | None = None
) -> list[int]:
    """Disable the account and cancel its queued and running submissions (a running one's
    worker sees the state and stops); the ids of those cancelled."""
    now = now or utcnow()
    accounts.disable_user(db, user=user, by=by, reason=reason, now=now)
    unfinished = db.execute(
        select(Submission.id, Submission.attempt)
        .where(Submission.user_id == user.id, Submission.state.in_(ACTIVE_STATES))
        .order_by(Submission.id)
    ).all()
    return [
        submission_id
        for submission_id, attempt in unfinished
        if transition(db, submission_id, attempt, State.CANCELLED, CANCEL_REASON, now=now)
    ]
