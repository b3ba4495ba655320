"""Request and response bodies of the teams API."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import BaseModel, Field

from server.accounts.schemas import USERNAME_PATTERN
from server.kit.schemas import InBody, Line
from server.teams.service import DISPLAY_NAME_MAX, TEAM_NAME_PATTERN

TeamName = Annotated[
    str,
    Field(
        min_length=3,
        max_length=32,
        pattern=TEAM_NAME_PATTERN,
        description="lowercase letters, digits, '-' and '_': the team's page is /teams/{name}",
    ),
]
Username = Annotated[str, Field(min_length=3, max_length=32, pattern=USERNAME_PATTERN)]


class TeamIn(InBody):
    name: TeamName
    display_name: Annotated[Line, Field(min_length=1, max_length=DISPLAY_NAME_MAX)]


class InviteIn(InBody):
    username: Username


class MemberOut(BaseModel):
    username: str
    is_admin: bool = Field(description="The team's admin: invites, revokes and removes.")
    joined_at: datetime


class InvitationOut(BaseModel):
    id: int
    team: str
    team_display_name: str
    username: str = Field(description="Who is invited.")
    invited_by: str | None = Field(description="Who sent it (null: that account is gone).")
    created_at: datetime


class TeamOut(BaseModel):
    name: str
    display_name: str
    created_at: datetime
    members: list[MemberOut] = Field(description="The admin first, then by joining.")
    invitations: list[InvitationOut] | None = Field(
        description="Pending invitations: shown to the team's admin only (null for others)."
    )


class MyTeamOut(BaseModel):
    team: TeamOut | None = Field(description="The caller's team; null when not in one.")
    invitations: list[InvitationOut] = Field(description="Invitations waiting for an answer.")


class LeftOut(BaseModel):
    team: str
    dissolved: bool = Field(description="The caller was its last member: the team is gone.")
