"""Submissions: accept, quota, the state machine, cancel and re-run.

Every state change is one conditional ``UPDATE ... WHERE state IN (...) AND attempt = ...``:
of two workers racing the same submission exactly one changes it, and the loser learns so from
the row count. Each change is recorded in ``transitions`` with its time and reason. Work for
the queue is written to the ``outbox`` in the same transaction and sent after the commit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session as DB

from server.errors import Conflict, Forbidden, Invalid, NotFound, QuotaExceeded
from server.models import (
    ACTIVE_STATES,
    FINAL_STATES,
    Challenge,
    Outbox,
    Phase,
    State,
    Submission,
    Transition,
    User,
    utcnow,
)

# Which states each state may move to (re-run, a new attempt, is separate: final -> queued).
ALLOWED: dict[State, frozenset[State]] = {
    State.QUEUED: frozenset({State.LAUNCHING, State.CANCELLED, State.ERROR}),
    State.LAUNCHING: frozenset(
        {State.RUNNING, State.CANCELLED, State.ERROR, State.FAILED, State.TIMED_OUT}
    ),
    State.RUNNING: frozenset(
        {State.SUCCEEDED, State.FAILED, State.ERROR, State.CANCELLED, State.TIMED_OUT}
    ),
}
# A submission reserves quota from the moment it is accepted; if it ends in `error` (our
# fault) or `cancelled` the reservation is released. Running and policy-caused endings count.
QUOTA_HOLDING = frozenset(
    {State.QUEUED, State.LAUNCHING, State.RUNNING, State.SUCCEEDED, State.FAILED, State.TIMED_OUT}
)
DAY = timedelta(days=1)
LOCAL_PREFIX = "local:"


@dataclass(frozen=True)
class Resolved:
    """What the image resolver returns: the reference to run, pinned, and its size."""

    pinned: str
    size_bytes: int | None


Resolver = Callable[[str], Resolved]


def sources_from(states: Iterable[State], target: State) -> list[State]:
    return [s for s in states if target in ALLOWED.get(s, frozenset())]


def submit(
    db: DB,
    user: User,
    challenge: Challenge,
    phase: Phase,
    *,
    image: str,
    description: str,
    public: bool,
    resolve: Resolver,
    now: datetime | None = None,
) -> Submission:
    """Accept a submission (state `queued`) or raise; the caller commits, then dispatches."""
    now = now or utcnow()
    if len(description) > 2000:
        raise Invalid("description too long", fields={"description": "at most 2000 characters"})
    if not phase.is_open(now):
        when = phase.opens_at if phase.opens_at and now < phase.opens_at else phase.closes_at
        verb = "opens" if phase.opens_at and now < phase.opens_at else "closed"
        raise Conflict(
            f"phase {phase.name!r} of {challenge.slug!r} {verb} at {when:%Y-%m-%d %H:%M} UTC",
            fields={"phase": f"not open for submissions ({verb})"},
        )
    # Resolve before taking the lock: it talks to the registry.
    resolved = resolve(image)

    # Serialise this user's submissions so that two concurrent ones cannot both pass the quota.
    db.execute(select(User.id).where(User.id == user.id).with_for_update())
    check_quota(db, user, challenge, now=now)

    submission = Submission(
        user_id=user.id,
        challenge_id=challenge.id,
        phase_id=phase.id,
        image=image,
        pinned_image=resolved.pinned,
        image_bytes=resolved.size_bytes,
        description=description,
        public=public,
        state=State.QUEUED,
        reason="waiting for a worker",
        attempt=1,
        created_at=now,
        updated_at=now,
    )
    db.add(submission)
    db.flush()
    db.add(
        Transition(
            submission_id=submission.id,
            attempt=1,
            from_state=None,
            to_state=State.QUEUED,
            reason="submitted",
            at=now,
        )
    )
    db.add(Outbox(submission_id=submission.id, attempt=1, created_at=now))
    db.flush()
    return submission


@dataclass(frozen=True)
class QuotaUse:
    per_day_used: int
    per_day_limit: int
    concurrent_used: int
    concurrent_limit: int
    resets_at: datetime | None


def quota_use(db: DB, user: User, challenge: Challenge, *, now: datetime) -> QuotaUse:
    base = select(Submission.created_at).where(
        Submission.user_id == user.id, Submission.challenge_id == challenge.id
    )
    day = db.scalars(
        base.where(Submission.created_at > now - DAY, Submission.state.in_(QUOTA_HOLDING)).order_by(
            Submission.created_at
        )
    ).all()
    active = db.scalar(
        select(func.count())
        .select_from(Submission)
        .where(
            Submission.user_id == user.id,
            Submission.challenge_id == challenge.id,
            Submission.state.in_(ACTIVE_STATES),
        )
    )
    resets_at = day[0] + DAY if len(day) >= challenge.quota_per_day else None
    return QuotaUse(
        per_day_used=len(day),
        per_day_limit=challenge.quota_per_day,
        concurrent_used=active or 0,
        concurrent_limit=challenge.quota_concurrent,
        resets_at=resets_at,
    )


def check_quota(db: DB, user: User, challenge: Challenge, *, now: datetime) -> None:
    use = quota_use(db, user, challenge, now=now)
    if use.resets_at is not None:
        raise QuotaExceeded(
            f"daily quota of {use.per_day_limit} submissions to {challenge.slug!r} used; "
            f"the next one is possible at {use.resets_at:%Y-%m-%d %H:%M:%S} UTC",
            retry_after=(use.resets_at - now).total_seconds(),
            resets_at=use.resets_at.isoformat(),
        )
    if use.concurrent_used >= use.concurrent_limit:
        raise QuotaExceeded(
            f"{use.concurrent_used} of your submissions to {challenge.slug!r} are still "
            f"queued or running (limit {use.concurrent_limit}); wait for one to finish",
            retry_after=60,
            resets_at=None,
        )


def transition(
    db: DB,
    submission_id: int,
    attempt: int,
    to: State,
    reason: str,
    *,
    now: datetime | None = None,
    **values: Any,
) -> bool:
    """Move the submission to `to` if its current attempt is in a state that allows it.

    Returns False (and changes nothing) when another actor got there first.
    """
    now = now or utcnow()
    sources = sources_from(ALLOWED, to)
    if to == State.RUNNING:
        values.setdefault("started_at", now)
        values.setdefault("heartbeat_at", now)
    if to.final:
        values.setdefault("finished_at", now)
    previous: State | None = None
    for source in sources:  # one atomic conditional update per possible source state
        result = db.execute(
            update(Submission)
            .where(
                Submission.id == submission_id,
                Submission.attempt == attempt,
                Submission.state == source,
            )
            .values(state=to, reason=reason[:2000], updated_at=now, **values)
            .execution_options(synchronize_session=False)
        )
        if result.rowcount == 1:  # type: ignore[attr-defined]
            previous = source
            break
    if previous is None:
        return False
    db.add(
        Transition(
            submission_id=submission_id,
            attempt=attempt,
            from_state=previous,
            to_state=to,
            reason=reason[:2000],
            at=now,
        )
    )
    db.flush()
    return True


def visible_to(submission: Submission, user: User | None) -> bool:
    """Whether `user` may see this submission at all (others get 404, not 403)."""
    if user is not None and (user.is_admin or user.id == submission.user_id):
        return True
    return submission.public and not submission.hidden


def owned_or_admin(submission: Submission, user: User | None) -> bool:
    return user is not None and (user.is_admin or user.id == submission.user_id)


def get_visible(db: DB, submission_id: int, user: User | None) -> Submission:
    submission = db.get(Submission, submission_id)
    if submission is None or not visible_to(submission, user):
        raise NotFound(f"no submission {submission_id}")
    return submission


def cancel(db: DB, user: User, submission: Submission, *, now: datetime | None = None) -> None:
    """Cancel by the owner (or an admin): the worker sees the state and stops the run."""
    if not owned_or_admin(submission, user):
        raise NotFound(f"no submission {submission.id}")
    if submission.state in FINAL_STATES:
        raise Conflict(f"submission {submission.id} already ended ({submission.state.value})")
    who = "an admin" if user.id != submission.user_id else "its owner"
    if not transition(
        db, submission.id, submission.attempt, State.CANCELLED, f"cancelled by {who}", now=now
    ):
        db.refresh(submission)
        raise Conflict(f"submission {submission.id} already ended ({submission.state.value})")
    db.refresh(submission)


def edit(
    db: DB,
    user: User,
    submission: Submission,
    *,
    public: bool | None = None,
    hidden: bool | None = None,
    baseline: bool | None = None,
    description: str | None = None,
) -> None:
    """The owner changes visibility and description; admins also hide and flag baselines.
    The phase's leaderboard is recomputed for the submission's owner."""
    from server.leaderboard import refresh

    if not owned_or_admin(submission, user):
        raise NotFound(f"no submission {submission.id}")
    if (hidden is not None or baseline is not None) and not user.is_admin:
        raise Forbidden("only admins can hide submissions or flag baselines")
    changes: dict[str, bool | str | None] = {
        "public": public,
        "hidden": hidden,
        "baseline": baseline,
        "description": description,
    }
    for name, value in changes.items():
        if value is not None:
            setattr(submission, name, value)
    db.flush()
    refresh(db, submission.phase_id, submission.user_id)


def rerun(db: DB, admin: User, submission: Submission, *, now: datetime | None = None) -> None:
    """An admin runs an ended submission again, as a new attempt with its own results."""
    if not admin.is_admin:
        raise Forbidden("only admins can re-run submissions")
    if not new_attempt(db, submission, "re-run by an admin", now=now):
        raise Conflict(f"submission {submission.id} has not ended; cancel it first")


def new_attempt(
    db: DB,
    submission: Submission,
    reason: str,
    *,
    from_states: frozenset[State] = FINAL_STATES,
    now: datetime | None = None,
) -> bool:
    """Queue an ended submission again as attempt N+1 (its old results stay with attempt N).

    False when it is not in one of `from_states` any more (someone else acted first).
    """
    now = now or utcnow()
    old, previous = submission.attempt, submission.state
    result = db.execute(
        update(Submission)
        .where(
            Submission.id == submission.id,
            Submission.attempt == old,
            Submission.state.in_(from_states),
        )
        .values(
            attempt=old + 1,
            state=State.QUEUED,
            reason=reason,
            updated_at=now,
            started_at=None,
            finished_at=None,
            heartbeat_at=None,
            deadline_at=None,
            score=None,
            result=None,
            log_tail="",
            progress=None,
        )
        .execution_options(synchronize_session=False)
    )
    if result.rowcount != 1:  # type: ignore[attr-defined]
        return False
    db.add(
        Transition(
            submission_id=submission.id,
            attempt=old + 1,
            from_state=previous,
            to_state=State.QUEUED,
            reason=reason,
            at=now,
        )
    )
    db.add(Outbox(submission_id=submission.id, attempt=old + 1, created_at=now))
    db.flush()
    db.refresh(submission)
    from server.leaderboard import refresh

    refresh(db, submission.phase_id, submission.user_id)
    return True
