"""Work for the workers: fair claims, the evaluation an attempt runs, a restarted or stopped
worker's attempts. Its callers: the internal API (`internal.py`: claims, assignments, a
restarted worker), the embedded service when it stops (`manieval/service.py`: `end_stopped`),
and the queue position (`position.py`), which reuses `fair_order`.

A worker does not run "the message it was given": it claims the next submission by a fair
order, with a conditional update that only one worker can win. So a message delivered twice,
or one delivered after its submission was cancelled, costs nothing, and a participant who
queued many submissions cannot starve the others.
"""

from __future__ import annotations

from collections import Counter

from sqlalchemy import select
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import joinedload

from evaluator.plan import build_plan
from internal_api.schemas import Assignment
from server.challenges.service import suite_of
from server.kit.errors import Conflict, NotFound
from server.models import Cause, State, Submission
from server.submissions.reconcile import end_lost
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


def claim_next(
    db: DB, *, worker: str, max_running_per_user: int, commit: bool = True
) -> tuple[int, int] | None:
    """Move the fairest queued submission to `launching` for `worker` and return (id,
    attempt), or None. Commits: a claim is won or lost at once; with `commit=False` the caller
    commits once it holds what it hands out (the internal API: a database that fails in
    between must leave the submission queued, not claimed by a worker that never heard)."""
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
            if transition(db, sid, attempt, State.LAUNCHING, "starting the policy", worker=worker):
                if commit:
                    db.commit()
                return sid, attempt
        db.rollback()
        if not order:
            return None  # everyone waiting is at their cap
    return None


def assignment(db: DB, *, submission_id: int, attempt: int, seed_secret: bytes) -> Assignment:
    """The evaluation of a current, active attempt, with its concrete seeds."""
    submission = db.get(
        Submission,
        submission_id,
        options=[joinedload(Submission.challenge), joinedload(Submission.phase)],
        populate_existing=True,
    )
    if submission is None:
        raise NotFound(f"no submission {submission_id}")
    if submission.attempt != attempt or submission.state not in (State.LAUNCHING, State.RUNNING):
        raise Conflict(f"attempt {attempt} of submission {submission_id} is not running")
    suite = suite_of(submission.challenge)
    # A secret-seed phase's episodes are the same hidden scenes for every entrant: a video
    # would show them (from the reset frame on) to whoever sees the submission.
    recorded = None if submission.phase.public_seeds else 0
    plan = build_plan(suite, submission.phase.name, secret=seed_secret, videos=recorded)
    return Assignment(
        submission_id=submission_id,
        attempt=attempt,
        image=submission.pinned_image,
        plan=plan,
        suite_yaml=submission.challenge.suite_yaml,
        shards=max(1, min(suite.shards, plan.episode_count())),
        evaluator_image=submission.challenge.evaluator_image,
    )


def end_restarted(db: DB, *, worker: str) -> list[int]:
    """A worker restarted: the attempts it had claimed and not ended died with it. They end
    `error` (ours: no quota) and run again once, as lost attempts do."""
    ended = []
    for s in db.scalars(
        select(Submission).where(
            Submission.worker == worker,
            Submission.state.in_([State.LAUNCHING, State.RUNNING]),
        )
    ):
        if end_lost(db, s, cause=Cause.WORKER_RESTARTED) is not None:
            ended.append(s.id)
    return ended


def end_stopped(db: DB, *, worker: str) -> list[int]:
    """The service stopped `worker` mid-evaluation (Ctrl-C, SIGTERM): the attempts it had
    claimed and not ended were interrupted. They end `error` (ours: no quota) and are queued
    again, every time: a stop is the operator's doing, not a sign of a policy that crashes
    its worker."""
    ended = []
    for s in db.scalars(
        select(Submission).where(
            Submission.worker == worker,
            Submission.state.in_([State.LAUNCHING, State.RUNNING]),
        )
    ):
        if end_lost(db, s, cause=Cause.STOPPED) is not None:
            ended.append(s.id)
    return ended
