"""The teams API, ``/api/v1``: create a team, invite by user name, accept or decline, revoke,
leave, remove a member (docs/server.md, Teams)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter
from fastapi import Path as FastAPIPath
from sqlalchemy.orm import Session as DB

from server.accounts.deps import CallerDep, UserDep
from server.kit.deps import DBDep, Id
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import Ok
from server.models import Team, TeamInvitation, User, team_of
from server.teams import service as teams
from server.teams.schemas import (
    InvitationOut,
    InviteIn,
    LeftOut,
    MemberOut,
    MyTeamOut,
    TeamIn,
    TeamName,
    TeamOut,
    Username,
)

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES, tags=["teams"])
NamePath = Annotated[TeamName, FastAPIPath()]
UserPath = Annotated[Username, FastAPIPath()]


def invitation_out(invitation: TeamInvitation, inviter: str | None) -> InvitationOut:
    return InvitationOut(
        id=invitation.id,
        team=invitation.team.name,
        team_display_name=invitation.team.display_name,
        username=invitation.user.username,
        invited_by=inviter,
        created_at=invitation.created_at,
    )


def team_out(db: DB, team: Team, viewer: User | None) -> TeamOut:
    view = teams.show_team(db, team=team, viewer=viewer)
    pending = view.invitations
    inviters = teams.inviter_names(db, invitations=pending or [])
    return TeamOut(
        name=team.name,
        display_name=team.display_name,
        created_at=team.created_at,
        members=[
            MemberOut(username=m.user.username, is_admin=m.is_admin, joined_at=m.joined_at)
            for m in view.members
        ],
        invitations=None
        if pending is None
        else [invitation_out(i, inviters.get(i.id)) for i in pending],
    )


@router.post("/teams", status_code=201)
def create_team(body: TeamIn, user: UserDep, db: DBDep) -> TeamOut:
    """Create a team with you as its admin (you must not be in a team)."""
    team = teams.create_team(db, user=user, name=body.name, display_name=body.display_name)
    db.commit()
    return team_out(db, team, user)


@router.get("/teams/{name}")
def show_team(name: NamePath, who: CallerDep, db: DBDep) -> TeamOut:
    """A team and its members (anyone may look; its admin also sees pending invitations)."""
    return team_out(db, teams.get_team(db, name=name), who.user)


@router.get("/team")
def my_team(user: UserDep, db: DBDep) -> MyTeamOut:
    """Your team (null when you are in none) and the invitations waiting for your answer."""
    team = team_of(db, user_id=user.id)
    mine = teams.invitations_for(db, user=user)
    inviters = teams.inviter_names(db, invitations=mine)
    return MyTeamOut(
        team=team_out(db, team, user) if team is not None else None,
        invitations=[invitation_out(i, inviters.get(i.id)) for i in mine],
    )


@router.post("/teams/{name}/invitations", status_code=201)
def invite(name: NamePath, body: InviteIn, user: UserDep, db: DBDep) -> InvitationOut:
    """Invite a user by name (the team's admin only)."""
    team = teams.get_team(db, name=name)
    invitation = teams.invite(db, admin=user, team=team, username=body.username)
    db.commit()
    return invitation_out(invitation, user.username)


@router.delete("/teams/{name}/invitations/{invitation_id}")
def revoke(name: NamePath, invitation_id: Id, user: UserDep, db: DBDep) -> Ok:
    """Withdraw a pending invitation (the team's admin only)."""
    teams.revoke(db, admin=user, team=teams.get_team(db, name=name), invitation_id=invitation_id)
    db.commit()
    return Ok()


@router.delete("/teams/{name}/members/{username}")
def remove_member(name: NamePath, username: UserPath, user: UserDep, db: DBDep) -> Ok:
    """Remove a member (the team's admin only; to leave, use POST /team/leave)."""
    teams.remove(db, admin=user, team=teams.get_team(db, name=name), username=username)
    db.commit()
    return Ok()


@router.post("/team/invitations/{invitation_id}/accept")
def accept(invitation_id: Id, user: UserDep, db: DBDep) -> TeamOut:
    """Join the team that invited you (you must not be in a team)."""
    team = teams.accept(db, user=user, invitation_id=invitation_id)
    db.commit()
    return team_out(db, team, user)


@router.post("/team/invitations/{invitation_id}/decline")
def decline(invitation_id: Id, user: UserDep, db: DBDep) -> Ok:
    """Turn an invitation down."""
    teams.decline(db, user=user, invitation_id=invitation_id)
    db.commit()
    return Ok()


@router.post("/team/leave")
def leave(user: UserDep, db: DBDep) -> LeftOut:
    """Leave your team. An admin who leaves hands the role to the member who joined first; the
    last member to leave dissolves the team."""
    team = team_of(db, user_id=user.id)
    name = team.name if team is not None else ""
    kept = teams.leave(db, user=user)
    db.commit()
    return LeftOut(team=name, dissolved=kept is None)
