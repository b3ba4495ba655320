"""Which queued submission runs next: fair between users, and never two runs of one attempt.

A worker does not run "the message it was given": it claims the next submission by a fair
order, with a conditional update that only one worker can win. So a message delivered twice,
or one delivered after its submission was cancelled, costs nothing, and a participant who
queued many submissions cannot starve the others.
"""

from __future__ import annotations

from collections import Counter

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.models import State, Submission
from server.submissions.states import transition

CLAIM_ATTEMPTS = 5


def fair_order(
    queued: list[tuple[int, int, int]], running_per_user: Counter[int], cap: int
) -> list[tuple[int, int]]:
    """Order queued (id, attempt, user) oldest-first input so that users interleave.

    Users at `cap` running evaluations are skipped; among the others, the user with the fewest
    running goes first, then the user whose oldest queued submission is oldest; each user's
    own submissions keep their order. Pure, for testing.
    """
    running = Counter(running_per_user)
    first_seen: dict[int, int] = {}
    per_user: dict[int, list[tuple[int, int]]] = {}
    for position, (sid, attempt, user) in enumerate(queued):
        first_seen.setdefault(user, position)
        per_user.setdefault(user, []).append((sid, attempt))
    order: list[tuple[int, int]] = []
    while True:
        ready = [u for u, items in per_user.items() if items and running[u] < cap]
        if not ready:
            return order
        user = min(ready, key=lambda u: (running[u], first_seen[u]))
        order.append(per_user[user].pop(0))
        running[user] += 1


def claim_next(db: DB, *, max_running_per_user: int) -> tuple[int, int] | None:
    """Move the fairest queued submission to `launching` and return (id, attempt), or None."""
    for _ in range(CLAIM_ATTEMPTS):
        queued = db.execute(
            select(Submission.id, Submission.attempt, Submission.user_id)
            .where(Submission.state == State.QUEUED)
            .order_by(Submission.updated_at, Submission.id)
            .limit(500)
        ).all()
        if not queued:
            return None
        running = Counter(
            db.scalars(
                select(Submission.user_id).where(
                    Submission.state.in_([State.LAUNCHING, State.RUNNING])
                )
            ).all()
        )
        order = fair_order([(s, a, u) for s, a, u in queued], running, max_running_per_user)
        for sid, attempt in order:
            if transition(db, sid, attempt, State.LAUNCHING, "starting the policy"):
                db.commit()
                return sid, attempt
        db.rollback()
        if not order:
            return None  # everyone waiting is at their cap
    return None
