"""Quotas: how many submissions a participant may make to a challenge per rolling day and have
queued or running at once. In a challenge with team mode on, a team's members share one quota
(docs/server.md, Teams)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import ColumnElement, func, or_, select
from sqlalchemy.orm import Session as DB

from server.challenges.tracks import quota_group
from server.kit.errors import QuotaExceeded
from server.models import (
    ACTIVE_STATES,
    Challenge,
    State,
    Submission,
    Team,
    TeamMember,
    User,
    team_id_of,
    team_of,
)

# A submission reserves quota from the moment it is accepted; if it ends in `error` (our
# fault) or `cancelled` the reservation is released. Running and policy-caused endings count.
# A re-evaluation (`Submission.reevaluation_of`) holds none, in any state.
QUOTA_HOLDING = frozenset(
    {State.QUEUED, State.LAUNCHING, State.RUNNING, State.SUCCEEDED, State.FAILED, State.TIMED_OUT}
)
DAY = timedelta(days=1)


@dataclass(frozen=True)
class QuotaUse:
    per_day_used: int
    per_day_limit: int
    concurrent_used: int
    concurrent_limit: int
    resets_at: datetime | None
    team: str | None = None
    """The team whose members share this quota (team mode), or None: the user's own."""
    shared_by: int = 1
    """How many tracks' submissions count against it (docs/server.md, Tracks)."""
    quota_of: str = ""
    """The challenge whose quota it is: the group's head when its tracks share one."""


def _team(db: DB, *, user: User, challenge: Challenge) -> Team | None:
    """The team whose quota the user draws on: theirs, in a challenge with team mode on."""
    return team_of(db, user_id=user.id) if challenge.team_mode else None


def _counted(user: User, team: Team | None) -> ColumnElement[bool]:
    """The submissions a quota counts: the user's own; for a team, every current member's
    (what they made before joining too) and every one made in the team (by members who left
    too), so that neither joining nor leaving a team hands out quota. A dissolved team is
    nobody's: what was made in it counts for its submitters, by `user_id`."""
    if team is None:
        return Submission.user_id == user.id
    members = select(TeamMember.user_id).where(TeamMember.team_id == team.id)
    return or_(Submission.team_id == team.id, Submission.user_id.in_(members))


def quota_use(db: DB, *, user: User, challenge: Challenge, now: datetime) -> QuotaUse:
    """How much of the challenge's daily and concurrent quota the user (or their team) holds."""
    team = _team(db, user=user, challenge=challenge)
    limits, challenge_ids = quota_group(db, challenge)
    counted = (
        _counted(user, team),
        Submission.challenge_id.in_(challenge_ids),
        Submission.reevaluation_of.is_(None),  # an organizer's re-evaluation: nobody's quota
    )
    day = db.scalars(
        select(Submission.created_at)
        .where(*counted, Submission.created_at > now - DAY, Submission.state.in_(QUOTA_HOLDING))
        .order_by(Submission.created_at)
    ).all()
    active = db.scalar(
        select(func.count())
        .select_from(Submission)
        .where(*counted, Submission.state.in_(ACTIVE_STATES))
    )
    resets_at = day[0] + DAY if len(day) >= limits.quota_per_day else None
    return QuotaUse(
        per_day_used=len(day),
        per_day_limit=limits.quota_per_day,
        concurrent_used=active or 0,
        concurrent_limit=limits.quota_concurrent,
        resets_at=resets_at,
        team=team.name if team is not None else None,
        shared_by=len(challenge_ids),
        quota_of=limits.slug,
    )


def check_quota(db: DB, *, user: User, challenge: Challenge, now: datetime) -> int | None:
    """Serialise the user's submissions (in team mode their team's too), then raise
    QuotaExceeded (with when to try again) if they may not submit now. Returns the user's team
    id, which the new submission records, or None."""
    # Lock the user, then their team: two submissions of one user, or of two members of one
    # team, cannot both pass the quota. Team changes take the same locks in the same order.
    db.execute(select(User.id).where(User.id == user.id).with_for_update(key_share=True))
    team_id = team_id_of(db, user_id=user.id)
    if team_id is not None and challenge.team_mode:
        db.execute(select(Team.id).where(Team.id == team_id).with_for_update(key_share=True))
    use = quota_use(db, user=user, challenge=challenge, now=now)
    whose = f"team {use.team}'s" if use.team else "your"
    if use.resets_at is not None:
        raise QuotaExceeded(
            f"{'' if use.team is None else whose + ' '}daily quota of {use.per_day_limit} "
            f"submissions to {_whose_quota(use)} used; the next one is possible at "
            f"{use.resets_at:%Y-%m-%d %H:%M:%S} UTC",
            retry_after=(use.resets_at - now).total_seconds(),
            resets_at=use.resets_at.isoformat(),
        )
    if use.concurrent_used >= use.concurrent_limit:
        raise QuotaExceeded(
            f"{use.concurrent_used} of {whose} submissions to {_whose_quota(use)} are still "
            f"queued or running (limit {use.concurrent_limit}); wait for one to finish",
            retry_after=60,
            resets_at=None,
        )
    return team_id


def _whose_quota(use: QuotaUse) -> str:
    tracks = f" and its tracks (one quota for {use.shared_by})" if use.shared_by > 1 else ""
    return f"{use.quota_of!r}{tracks}"
