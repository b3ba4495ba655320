"""Team pages: a team's page (members; for its admin the invite form and pending
invitations), and "your team" (create one, answer invitations, leave)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Form, Path, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.accounts.deps import PostedDep, ViewerDep
from server.kit.deps import DBDep, Id
from server.kit.errors import AppError
from server.kit.pages import Viewer, redirect, render, signed_in
from server.models import Team, User, team_of
from server.teams import service as teams

router = APIRouter(include_in_schema=False)

Text = Annotated[str, Form(max_length=1024)]
Done = Annotated[str, Query(max_length=20)]
NamePath = Annotated[str, Path(max_length=64)]
NOTICES = {
    "created": "Your team is created: invite members by their user names on its page.",
    "joined": "You joined the team.",
    "declined": "The invitation is declined.",
    "left": "You left the team.",
    "dissolved": "You left the team; you were its last member, so it is dissolved.",
    "invited": "The invitation is sent: it shows on the invited user's team page.",
    "revoked": "The invitation is revoked.",
    "removed": "The member is removed from the team.",
}


def _mine(request: Request, who: Viewer, db: DB, **context: Any) -> Response:
    user = signed_in(request, who)
    team = team_of(db, user_id=user.id)
    invitations = teams.invitations_for(db, user=user)
    context = {"errors": {}, "message": "", "notice": "", "form": {}, **context}
    return render(
        request,
        who,
        "team_mine.html",
        user=user,
        view=teams.show_team(db, team=team, viewer=user) if team is not None else None,
        invitations=invitations,
        inviters=teams.inviter_names(db, invitations=invitations),
        **context,
    )


def _team_page(request: Request, who: Viewer, db: DB, team: Team, **context: Any) -> Response:
    user: User | None = who.user
    view = teams.show_team(db, team=team, viewer=user)
    context = {"errors": {}, "message": "", "notice": "", "form": {}, **context}
    return render(
        request,
        who,
        "team.html",
        view=view,
        inviters=teams.inviter_names(db, invitations=view.invitations or []),
        me=next((m for m in view.members if user is not None and m.user_id == user.id), None),
        **context,
    )


@router.get("/team")
def my_team(request: Request, who: ViewerDep, db: DBDep, done: Done = "") -> Response:
    """Your team, or the form to create one; the invitations waiting for your answer."""
    return _mine(request, who, db, notice=NOTICES.get(done, ""))


@router.post("/team")
def create_team(
    request: Request, who: PostedDep, db: DBDep, name: Text = "", display_name: Text = ""
) -> Response:
    user = signed_in(request, who)
    try:
        team = teams.create_team(db, user=user, name=name, display_name=display_name)
        db.commit()
    except AppError as exc:
        db.rollback()
        form = {"name": name, "display_name": display_name}
        errors = exc.fields or {"name": exc.message}
        return _mine(request, who, db, errors=errors, message=exc.message, form=form)
    return redirect(f"/teams/{team.name}?done=created")


@router.post("/team/invitations/{invitation_id}/accept")
def accept(request: Request, invitation_id: Id, who: PostedDep, db: DBDep) -> Response:
    user = signed_in(request, who)
    try:
        team = teams.accept(db, user=user, invitation_id=invitation_id)
        db.commit()
    except AppError as exc:
        db.rollback()
        return _mine(request, who, db, message=exc.message)
    return redirect(f"/teams/{team.name}?done=joined")


@router.post("/team/invitations/{invitation_id}/decline")
def decline(request: Request, invitation_id: Id, who: PostedDep, db: DBDep) -> Response:
    user = signed_in(request, who)
    try:
        teams.decline(db, user=user, invitation_id=invitation_id)
        db.commit()
    except AppError as exc:
        db.rollback()
        return _mine(request, who, db, message=exc.message)
    return redirect("/team?done=declined")


@router.post("/team/leave")
def leave(request: Request, who: PostedDep, db: DBDep) -> Response:
    user = signed_in(request, who)
    try:
        kept = teams.leave(db, user=user)
        db.commit()
    except AppError as exc:
        db.rollback()
        return _mine(request, who, db, message=exc.message)
    return redirect("/team?done=" + ("left" if kept is not None else "dissolved"))


@router.get("/teams/{name}")
def team_page(
    request: Request, name: NamePath, who: ViewerDep, db: DBDep, done: Done = ""
) -> Response:
    """A team: its members; for its admin, the invite form and the pending invitations."""
    team = teams.get_team(db, name=name)
    return _team_page(request, who, db, team, notice=NOTICES.get(done, ""))


@router.post("/teams/{name}/invitations")
def invite(
    request: Request, name: NamePath, who: PostedDep, db: DBDep, username: Text = ""
) -> Response:
    user = signed_in(request, who)
    team = teams.get_team(db, name=name)
    try:
        teams.invite(db, admin=user, team=team, username=username.strip())
        db.commit()
    except AppError as exc:
        db.rollback()
        errors = exc.fields or {"username": exc.message}
        form = {"username": username}
        return _team_page(request, who, db, team, errors=errors, message=exc.message, form=form)
    return redirect(f"/teams/{team.name}?done=invited")


@router.post("/teams/{name}/invitations/{invitation_id}/revoke")
def revoke(
    request: Request, name: NamePath, invitation_id: Id, who: PostedDep, db: DBDep
) -> Response:
    user = signed_in(request, who)
    team = teams.get_team(db, name=name)
    try:
        teams.revoke(db, admin=user, team=team, invitation_id=invitation_id)
        db.commit()
    except AppError as exc:
        db.rollback()
        return _team_page(request, who, db, team, message=exc.message)
    return redirect(f"/teams/{team.name}?done=revoked")


@router.post("/teams/{name}/members/{username}/remove")
def remove(
    request: Request, name: NamePath, username: NamePath, who: PostedDep, db: DBDep
) -> Response:
    user = signed_in(request, who)
    team = teams.get_team(db, name=name)
    try:
        teams.remove(db, admin=user, team=team, username=username)
        db.commit()
    except AppError as exc:
        db.rollback()
        return _team_page(request, who, db, team, message=exc.message)
    return redirect(f"/teams/{team.name}?done=removed")
