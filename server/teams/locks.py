"""The row locks a membership change takes, in the one order every writer takes them: users
(id order), then teams (id order), as the quota check (`server.challenges.quota`) and a
leaderboard refresh (`server.standings.entries`) do. A change locks up front every row the
boards it recomputes will lock, so that no user row is locked after a team row.

Every such lock is FOR NO KEY UPDATE (`key_share=True`): it serialises these writers but not
the foreign-key checks of rows that merely point at a user or a team (an invitation naming its
inviter), which would otherwise close a cycle with a writer holding that row."""

from __future__ import annotations

from collections.abc import Iterable

from sqlalchemy import func, select
from sqlalchemy.orm import Session as DB

from server.models import Submission, Team, TeamMember, User


def hold(db: DB, *, users: Iterable[int], teams: Iterable[int] = ()) -> None:
    """Lock the users' rows, then the rows of `teams` and of every team those users submitted
    in (whose boards a refresh of those users recomputes). Rows already held are no-ops."""
    user_ids = sorted(set(users))
    for user_id in user_ids:
        db.execute(select(User.id).where(User.id == user_id).with_for_update(key_share=True))
    submitted = db.scalars(
        select(Submission.team_id)
        .where(Submission.user_id.in_(user_ids), Submission.team_id.is_not(None))
        .distinct()
    ).all()
    team_ids = {t for t in submitted if t is not None} | set(teams)
    for team_id in sorted(team_ids):
        db.execute(select(Team.id).where(Team.id == team_id).with_for_update(key_share=True))


def membership(db: DB, *, user_id: int) -> TeamMember | None:
    """The user's membership as the database has it now (read after the locks: the admin flag
    changes under the team's lock, not the user's)."""
    return db.scalar(
        select(TeamMember)
        .where(TeamMember.user_id == user_id)
        .execution_options(populate_existing=True)
    )


def locked_team(db: DB, *, team_id: int) -> Team | None:
    """The team, its row locked and read fresh; None once it is dissolved (or gone)."""
    team = db.scalar(
        select(Team)
        .where(Team.id == team_id)
        .with_for_update(key_share=True)
        .execution_options(populate_existing=True)
    )
    return team if team is not None and team.dissolved_at is None else None


def member_count(db: DB, *, team_id: int) -> int:
    """How many members the team has."""
    return (
        db.scalar(select(func.count()).select_from(TeamMember).where(TeamMember.team_id == team_id))
        or 0
    )


def submitters(db: DB, *, team_id: int) -> set[int]:
    """Who made submissions in the team: the rows its dissolution recomputes."""
    return set(
        db.scalars(select(Submission.user_id).where(Submission.team_id == team_id).distinct())
    )
