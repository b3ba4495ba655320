"""Teams: a user creates one, invites users by name, who accept or decline; members leave,
the team's admin removes them. The rules (docs/server.md, Teams):

- a user is in at most one team at a time (teams are not per challenge);
- the creator is the team's admin; when the admin leaves, the member who joined first becomes
  admin; when the last member leaves the team is dissolved: its row stays, marked, with its
  name freed, and the submissions made in it count as their submitters' own again;
- invitations are single-use (accepting, declining or revoking deletes them);
- every membership change recomputes the boards of challenges in team mode.

Locks (`server.teams.locks`): users' rows, then teams' rows, each in id order, as the quota
check takes them: a member cannot join or leave while a submission of theirs is being counted.
Every rule is checked on what is read after the locks are held.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import joinedload

from server.accounts import service as accounts
from server.kit.errors import Conflict, Forbidden, Invalid, NotFound
from server.kit.schemas import text_problem
from server.kit.security import RESERVED_USERNAMES, TEAM_NAME_GRAMMAR
from server.models import Team, TeamInvitation, TeamMember, User, team_id_of, utcnow
from server.standings.entries import refresh_member, release_team
from server.teams import locks

TEAM_NAME_PATTERN = rf"^{TEAM_NAME_GRAMMAR}$"
"""A team's name: lowercase letters, digits, '-' and '_' (a user name may also hold capitals)."""
_TEAM_NAME = re.compile(TEAM_NAME_PATTERN)
DISPLAY_NAME_MAX = 64
MAX_PENDING = 50
"""Pending invitations a team may have at once: bounds what one admin can send."""


def validate_team_name(name: str) -> str | None:
    """Why `name` cannot be a team's name, or None when it can."""
    if not 3 <= len(name) <= 32:
        return "A team name must be 3 to 32 characters long."
    if not _TEAM_NAME.fullmatch(name):
        return (
            "A team name may contain only lowercase letters a-z, digits, '-' and '_', "
            "starting and ending with a letter or digit."
        )
    if name in RESERVED_USERNAMES:  # a team must not pass for the service or its staff either
        return "This team name is reserved; choose another."
    return None


def _display_name(value: str) -> str:
    name = value.strip()
    problem = text_problem(name)
    if problem is None and not name:
        problem = "A display name is required."
    if problem is None and len(name) > DISPLAY_NAME_MAX:
        problem = f"At most {DISPLAY_NAME_MAX} characters."
    if problem is not None:
        raise Invalid(problem, fields={"display_name": problem})
    return name


@dataclass(frozen=True)
class TeamView:
    """A team as its page shows it: members (admin first, then by joining) and, for its
    admin (and, to read only, a site admin), the pending invitations."""

    team: Team
    members: list[TeamMember]
    invitations: list[TeamInvitation] | None
    manages: bool = False
    """Whether the viewer is the team's admin: who invites, revokes and removes."""

    def admin(self) -> TeamMember | None:
        return next((m for m in self.members if m.is_admin), None)


def get_team(db: DB, *, name: str) -> Team:
    """The team of this name, or NotFound (a dissolved team is not found)."""
    team = db.scalar(select(Team).where(Team.name == name, Team.dissolved_at.is_(None)))
    if team is None:
        raise NotFound(f"no team {name!r}")
    return team


def show_team(db: DB, *, team: Team, viewer: User | None) -> TeamView:
    """The team with its members; its pending invitations when `viewer` is its admin (or a
    site admin, who sees them but cannot act on them)."""
    members = list(
        db.scalars(
            select(TeamMember)
            .options(joinedload(TeamMember.user))
            .where(TeamMember.team_id == team.id)
            .order_by(TeamMember.is_admin.desc(), TeamMember.joined_at, TeamMember.user_id)
        )
    )
    manages = viewer is not None and any(m.user_id == viewer.id and m.is_admin for m in members)
    invitations = None
    if manages or (viewer is not None and viewer.is_admin):
        invitations = list(
            db.scalars(
                select(TeamInvitation)
                .options(joinedload(TeamInvitation.user), joinedload(TeamInvitation.team))
                .where(TeamInvitation.team_id == team.id)
                .order_by(TeamInvitation.created_at, TeamInvitation.id)
            )
        )
    return TeamView(team=team, members=members, invitations=invitations, manages=manages)


def invitations_for(db: DB, *, user: User) -> list[TeamInvitation]:
    """The invitations waiting for the user's answer, oldest first."""
    return list(
        db.scalars(
            select(TeamInvitation)
            .options(joinedload(TeamInvitation.team), joinedload(TeamInvitation.user))
            .where(TeamInvitation.user_id == user.id)
            .order_by(TeamInvitation.created_at, TeamInvitation.id)
        )
    )


def inviter_names(db: DB, *, invitations: list[TeamInvitation]) -> dict[int, str]:
    """Who sent each invitation (by invitation id), where that user still exists."""
    ids = {i.invited_by_id for i in invitations if i.invited_by_id is not None}
    if not ids:
        return {}
    rows = db.execute(select(User.id, User.username).where(User.id.in_(ids))).all()
    names = {row.id: row.username for row in rows}
    return {
        i.id: names[i.invited_by_id]
        for i in invitations
        if i.invited_by_id is not None and i.invited_by_id in names
    }


def create_team(db: DB, *, user: User, name: str, display_name: str) -> Team:
    """Create a team with `user` as its admin and only member."""
    if (problem := validate_team_name(name)) is not None:
        raise Invalid(problem, fields={"name": problem})
    shown = _display_name(display_name)
    locks.hold(db, users={user.id})
    if (current := team_id_of(db, user_id=user.id)) is not None:
        raise Conflict(_in_team(db, current), fields={"name": _in_team(db, current)})
    if db.scalar(select(Team.id).where(Team.name == name)) is not None:
        raise Conflict(f"the team name {name!r} is taken", fields={"name": "taken"})
    team = Team(name=name, display_name=shown, created_at=utcnow())
    db.add(team)
    try:
        db.flush()
    except IntegrityError:  # a team of this name was created at the same moment
        db.rollback()
        raise Conflict(f"the team name {name!r} is taken", fields={"name": "taken"}) from None
    db.add(TeamMember(team_id=team.id, user_id=user.id, is_admin=True, joined_at=utcnow()))
    db.flush()
    refresh_member(db, user_id=user.id)
    return team


def _in_team(db: DB, team_id: int) -> str:
    name = db.scalar(select(Team.name).where(Team.id == team_id))
    return f"you are in team {name!r}: leave it first (a user is in one team at a time)"


def _locked(db: DB, team: Team) -> Team:
    name = team.name  # before the fresh read: a dissolved team's is its tombstone
    if (locked := locks.locked_team(db, team_id=team.id)) is None:
        raise NotFound(f"no team {name!r}: it was dissolved")
    return locked


def _require_admin(db: DB, *, team: Team, user: User) -> None:
    """Raise Forbidden unless `user` is the team's admin (call with the team's row locked)."""
    admin = db.scalar(
        select(TeamMember.is_admin).where(
            TeamMember.team_id == team.id, TeamMember.user_id == user.id
        )
    )
    if not admin:
        raise Forbidden(f"only the admin of team {team.name!r} can do this")


def invite(db: DB, *, admin: User, team: Team, username: str) -> TeamInvitation:
    """The team's admin invites a user by name (single-use until accepted, declined or
    revoked)."""
    team = _locked(db, team)  # serialises the team's invitations: the limit below is exact
    _require_admin(db, team=team, user=admin)
    invitee = accounts.user_named(db, username=username)
    if invitee is None:
        raise NotFound(f"no user {username!r}", fields={"username": "no such user"})
    if team_id_of(db, user_id=invitee.id) == team.id:
        raise Conflict(f"{username} is already in the team", fields={"username": "a member"})
    pending = db.scalar(
        select(func.count()).select_from(TeamInvitation).where(TeamInvitation.team_id == team.id)
    )
    if (pending or 0) >= MAX_PENDING:
        raise Conflict(f"the team has {MAX_PENDING} pending invitations: revoke some first")
    found = db.scalar(
        select(TeamInvitation.id).where(
            TeamInvitation.team_id == team.id, TeamInvitation.user_id == invitee.id
        )
    )
    if found is not None:
        raise Conflict(f"{username} is already invited", fields={"username": "already invited"})
    invitation = TeamInvitation(
        team=team, user=invitee, invited_by_id=admin.id, created_at=utcnow()
    )
    db.add(invitation)
    try:
        db.flush()
    except IntegrityError:  # the invitee's account was deleted meanwhile
        db.rollback()
        raise NotFound(f"no user {username!r}", fields={"username": "no such user"}) from None
    return invitation


def _invitation_for(db: DB, *, user: User, invitation_id: int) -> TeamInvitation:
    invitation = db.scalar(
        select(TeamInvitation)
        .options(joinedload(TeamInvitation.team))
        .where(TeamInvitation.id == invitation_id, TeamInvitation.user_id == user.id)
        .execution_options(populate_existing=True)
    )
    if invitation is None:
        raise NotFound(f"no invitation {invitation_id} for you")
    return invitation


def accept(db: DB, *, user: User, invitation_id: int) -> Team:
    """Join the team that invited the user; the invitation is used up."""
    if (current := team_id_of(db, user_id=user.id)) is not None:
        raise Conflict(_in_team(db, current))
    invited = _invitation_for(db, user=user, invitation_id=invitation_id)
    locks.hold(db, users={user.id}, teams={invited.team_id})
    # Read again under the locks: the user may have joined a team, the team been dissolved
    # (which deletes its invitations) or the invitation revoked meanwhile.
    if (current := team_id_of(db, user_id=user.id)) is not None:
        raise Conflict(_in_team(db, current))
    invitation = _invitation_for(db, user=user, invitation_id=invitation_id)
    team = _locked(db, invitation.team)
    db.delete(invitation)
    db.add(TeamMember(team_id=team.id, user_id=user.id, is_admin=False, joined_at=utcnow()))
    db.flush()
    refresh_member(db, user_id=user.id)
    return team


def decline(db: DB, *, user: User, invitation_id: int) -> None:
    """Turn an invitation down (it is deleted)."""
    db.delete(_invitation_for(db, user=user, invitation_id=invitation_id))
    db.flush()


def revoke(db: DB, *, admin: User, team: Team, invitation_id: int) -> None:
    """The team's admin withdraws a pending invitation."""
    team = _locked(db, team)
    _require_admin(db, team=team, user=admin)
    invitation = db.scalar(
        select(TeamInvitation).where(
            TeamInvitation.id == invitation_id, TeamInvitation.team_id == team.id
        )
    )
    if invitation is None:
        raise NotFound(f"no pending invitation {invitation_id} of team {team.name!r}")
    db.delete(invitation)
    db.flush()


def leave(db: DB, *, user: User) -> Team | None:
    """The user leaves their team; returns the team if it goes on, None if it was dissolved
    (they were its last member)."""
    held: set[int] = {user.id}
    while True:
        team_id = team_id_of(db, user_id=user.id)
        if team_id is None:
            raise Conflict("you are not in a team")
        if locks.member_count(db, team_id=team_id) <= 1:
            # Dissolving recomputes every submitter's rows: their users come before the team.
            held |= locks.submitters(db, team_id=team_id)
        locks.hold(db, users=held, teams={team_id})
        membership = locks.membership(db, user_id=user.id)
        if membership is None:
            raise Conflict("you are not in a team")
        dissolves = locks.member_count(db, team_id=membership.team_id) == 1
        if membership.team_id == team_id and (
            not dissolves or locks.submitters(db, team_id=team_id) <= held
        ):
            return _drop(db, membership)
        # What was read before the locks changed meanwhile (rare): another member left, so
        # this one dissolves the team and its submitters' rows are taken too, or the user
        # moved to another team. Go round with what is read now, under the user's lock.


def remove(db: DB, *, admin: User, team: Team, username: str) -> None:
    """The team's admin removes a member (to leave, the admin uses `leave`)."""
    member = accounts.user_named(db, username=username)
    member_id = None if member is None else member.id
    if member_id is not None and member_id != admin.id:
        locks.hold(db, users={member_id}, teams={team.id})
    team = _locked(db, team)
    _require_admin(db, team=team, user=admin)
    if member_id == admin.id:
        raise Conflict("to leave your own team, leave it (an admin is not removed)")
    membership = locks.membership(db, user_id=member_id) if member_id is not None else None
    if membership is None or membership.team_id != team.id:
        raise NotFound(f"{username} is not in team {team.name!r}")
    _drop(db, membership)


def _drop(db: DB, membership: TeamMember) -> Team | None:
    """End a membership (read after the locks: the user's, then the team's); hand the admin
    role on or dissolve an emptied team; recompute the boards."""
    team = db.get(Team, membership.team_id)
    assert team is not None
    user_id = membership.user_id
    db.delete(membership)
    db.flush()
    remaining = list(
        db.scalars(
            select(TeamMember)
            .where(TeamMember.team_id == team.id)
            .order_by(TeamMember.joined_at, TeamMember.user_id)
            .execution_options(populate_existing=True)
        )
    )
    if not remaining:
        _dissolve(db, team)
        refresh_member(db, user_id=user_id)
        return None
    if not any(m.is_admin for m in remaining):  # a team always has an admin
        remaining[0].is_admin = True
        db.flush()
    refresh_member(db, user_id=user_id)
    return team


def _dissolve(db: DB, team: Team) -> None:
    """Mark the emptied team dissolved; its name is free again; its invitations go."""
    db.execute(delete(TeamInvitation).where(TeamInvitation.team_id == team.id))
    team.dissolved_at = utcnow()
    team.name = f"~{team.id}"
    db.flush()
    release_team(db, team_id=team.id)
