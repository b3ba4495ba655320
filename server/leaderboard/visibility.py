"""Who sees which rows of a hidden board (a phase's `board: hidden`, not published yet):
organizers all of it, each participant their own rows and their team's, anyone else none
(docs/server.md, Challenge rules)."""

from __future__ import annotations

from fastapi import Request
from fastapi.security import HTTPAuthorizationCredentials
from sqlalchemy.orm import Session as DB

from server.accounts.deps import caller
from server.leaderboard.snapshot import Snapshot
from server.leaderboard.stored import Stored
from server.models import User, team_of


def as_seen_by(db: DB, board: Snapshot, *, user: User | None) -> Snapshot:
    """The board as `user` (None: anonymous) may see it."""
    if not board.hidden or (user is not None and user.is_admin):
        return board
    if user is None:
        return board.shown_to(organizer=False, own=lambda _row: False)
    team = team_of(db, user_id=user.id)
    name, team_name = user.username, team.name if team is not None else None

    def own(row: Stored) -> bool:
        if row.team_name is not None:
            return row.team_name == team_name
        return row.username == name

    return board.shown_to(organizer=False, own=own)


def as_seen_by_caller(db: DB, board: Snapshot, request: Request) -> Snapshot:
    """`as_seen_by` for the API's caller (an API token or the session cookie)."""
    header = request.headers.get("authorization") or ""
    scheme, _, token = header.partition(" ")
    credentials = HTTPAuthorizationCredentials(scheme=scheme, credentials=token) if header else None
    who = caller(request, db, credentials)
    return as_seen_by(db, board, user=who.user)
