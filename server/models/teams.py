"""Teams: a few users who take part together, their members and the invitations to join."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import Boolean, ForeignKey, String, UniqueConstraint, select
from sqlalchemy.orm import Mapped, Session, mapped_column, relationship

from server.models.accounts import User
from server.models.base import Base, utcnow


class Team(Base):
    """A team. In a challenge with team mode on, its members share one quota and one
    leaderboard row (docs/server.md, Teams)."""

    __tablename__ = "teams"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(32), unique=True)
    """The team's handle, as user names are written: its page is /teams/NAME. A dissolved
    team's is the tombstone `~ID`, outside that grammar, so its name is free again."""
    display_name: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    dissolved_at: Mapped[datetime | None] = mapped_column(default=None)
    """When its last member left. The row stays so that the submissions made in it keep their
    `team_id` (dissolving rewrites no submission); they count as their submitters' own."""


class TeamMember(Base):
    """A user's membership: the primary key is the user, so a user is in at most one team."""

    __tablename__ = "team_members"

    user_id: Mapped[int] = mapped_column(
        ForeignKey("users.id", ondelete="CASCADE"), primary_key=True
    )
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"), index=True)
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    """The team's admin invites, revokes and removes; the creator, then the oldest member."""
    joined_at: Mapped[datetime] = mapped_column(default=utcnow)

    user: Mapped[User] = relationship(lazy="raise")
    team: Mapped[Team] = relationship(lazy="raise")


class TeamInvitation(Base):
    """A pending invitation: accepting, declining or revoking it deletes it (single use)."""

    __tablename__ = "team_invitations"
    __table_args__ = (UniqueConstraint("team_id", "user_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"))
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    """Who is invited."""
    invited_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    team: Mapped[Team] = relationship(lazy="raise")
    user: Mapped[User] = relationship(lazy="raise", foreign_keys=[user_id])


def team_id_of(db: Session, *, user_id: int) -> int | None:
    """The id of the user's team, or None: the one reading of who is in which team (stable
    while the user's row is locked, as a submission and every team change lock it)."""
    return db.scalar(select(TeamMember.team_id).where(TeamMember.user_id == user_id))


def team_of(db: Session, *, user_id: int) -> Team | None:
    """The user's team, or None."""
    return db.scalar(
        select(Team)
        .join(TeamMember, TeamMember.team_id == Team.id)
        .where(TeamMember.user_id == user_id)
    )
