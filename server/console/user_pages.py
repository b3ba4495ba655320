"""The console's pages for accounts: the list (`/admin/users`, searched by name or address)
and one account's page with its actions: disable (with a reason) or enable, verify its
address, grant or revoke administrator rights. Administrators only."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server import audit
from server.accounts import service as accounts
from server.accounts.deps import PostedDep, ViewerDep
from server.console.forms import act_and_return
from server.console.records import shown
from server.console.users import disable_account
from server.kit.deps import DBDep, Id, PageNo
from server.kit.errors import AppError
from server.kit.pages import Viewer, admin_signed_in, render

router = APIRouter(include_in_schema=False)

PER_PAGE = 50
HISTORY = 20
DONE = {
    "disabled": "The account is disabled; its unfinished submissions are cancelled.",
    "enabled": "The account is enabled again.",
    "verified": "The account's address is marked verified.",
    "granted": "The account is an administrator now.",
    "revoked": "The account is no longer an administrator.",
}


@router.get("/admin/users")
def users(
    request: Request,
    who: ViewerDep,
    db: DBDep,
    q: Annotated[str, Query(max_length=254)] = "",
    page: PageNo = 1,
) -> Response:
    """Accounts, newest first, searched by part of a name or address."""
    admin_signed_in(request, who)
    rows, total = accounts.list_users(db, search=q, page=page, per_page=PER_PAGE)
    return render(
        request,
        who,
        "console/users.html",
        rows=rows,
        total=total,
        q=q,
        page=page,
        pages=max(1, -(-total // PER_PAGE)),
        pager_base="/admin/users?" + (urlencode({"q": q}) + "&" if q else ""),
    )


def _user_page(
    request: Request,
    who: Viewer,
    db: DB,
    user_id: int,
    *,
    error: AppError | None = None,
    form: dict[str, str] | None = None,
    done: str = "",
) -> Response:
    row = accounts.user_row(db, user=accounts.get_user(db, user_id=user_id))
    records = audit.records(db, target_kind="user", target_id=user_id, limit=HISTORY)
    return render(
        request,
        who,
        "console/user.html",
        row=row,
        records=shown(db, records),
        errors=error.fields if error is not None else {},
        message=error.message if error is not None else "",
        form=form or {},
        notice=DONE.get(done, ""),
    )


@router.get("/admin/users/{user_id}")
def user(
    user_id: Id,
    request: Request,
    who: ViewerDep,
    db: DBDep,
    done: Annotated[str, Query(max_length=20)] = "",
) -> Response:
    """One account: its state, its submissions, and what an administrator may do to it."""
    admin_signed_in(request, who)
    return _user_page(request, who, db, user_id, done=done)


def _attempt(
    request: Request,
    who: Viewer,
    db: DB,
    user_id: int,
    act: Callable[[], object],
    *,
    done: str,
    form: dict[str, str] | None = None,
) -> Response:
    """`act_and_return` on the account's page."""
    return act_and_return(
        db,
        act,
        page=f"/admin/users/{user_id}",
        done=done,
        refused=lambda exc: _user_page(request, who, db, user_id, error=exc, form=form),
    )


Reason = Annotated[str, Form(max_length=4000)]


@router.post("/admin/users/{user_id}/disable")
def disable(
    user_id: Id, request: Request, who: PostedDep, db: DBDep, reason: Reason = ""
) -> Response:
    """Disable the account (a reason is required: its owner is shown it)."""
    admin = admin_signed_in(request, who)

    def act() -> None:
        target = accounts.get_user(db, user_id=user_id)
        disable_account(db, user=target, by=admin, reason=reason)

    return _attempt(request, who, db, user_id, act, done="disabled", form={"reason": reason})


@router.post("/admin/users/{user_id}/enable")
def enable(user_id: Id, request: Request, who: PostedDep, db: DBDep) -> Response:
    admin = admin_signed_in(request, who)

    def act() -> None:
        accounts.enable_user(db, user=accounts.get_user(db, user_id=user_id), by=admin)

    return _attempt(request, who, db, user_id, act, done="enabled")


@router.post("/admin/users/{user_id}/verify")
def verify(user_id: Id, request: Request, who: PostedDep, db: DBDep) -> Response:
    admin = admin_signed_in(request, who)

    def act() -> None:
        accounts.mark_verified(db, user=accounts.get_user(db, user_id=user_id), by=admin)

    return _attempt(request, who, db, user_id, act, done="verified")


@router.post("/admin/users/{user_id}/admin")
def admin_rights(
    user_id: Id,
    request: Request,
    who: PostedDep,
    db: DBDep,
    admin: Annotated[str, Form(pattern="^(true|false)$")],
) -> Response:
    """Grant (`admin=true`) or revoke administrator rights; never one's own."""
    acting = admin_signed_in(request, who)
    grant = admin == "true"

    def act() -> None:
        target = accounts.get_user(db, user_id=user_id)
        accounts.set_admin(db, user=target, by=acting, admin=grant)

    return _attempt(request, who, db, user_id, act, done="granted" if grant else "revoked")
