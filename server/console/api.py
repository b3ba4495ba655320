"""The administrators' accounts API, `/api/v1/admin/users`: the list, disabling and enabling
an account, verifying its address, granting and revoking administrator rights."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from server.accounts import service as accounts
from server.accounts.deps import AdminDep, CallerDep, admin_of
from server.console.schemas import AdminUserOut, DisabledOut, ReasonIn
from server.console.users import disable_account
from server.kit.deps import DBDep, Id, PageNo, PerPage
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import Page
from server.models import User

router = APIRouter(prefix="/api/v1/admin", responses=ERROR_RESPONSES, tags=["admin"])
Search = Annotated[str, Query(max_length=254, description="part of a user name or address")]


def user_out(user: User, submissions: int) -> AdminUserOut:
    return AdminUserOut(
        id=user.id,
        username=user.username,
        email=user.email,
        email_verified=user.email_verified,
        is_admin=user.is_admin,
        created_at=user.created_at,
        disabled_at=user.disabled_at,
        disabled_reason=user.disabled_reason,
        submissions=submissions,
    )


def _out(db: DBDep, user: User) -> AdminUserOut:
    row = accounts.user_row(db, user=user)
    return user_out(row.user, row.submissions)


@router.get("/users")
def list_users(
    _admin: AdminDep, db: DBDep, q: Search = "", page: PageNo = 1, per_page: PerPage = 50
) -> Page[AdminUserOut]:
    """Accounts, newest first, whose name or address contains `q` (admins)."""
    rows, total = accounts.list_users(db, search=q, page=page, per_page=per_page)
    items = [user_out(row.user, row.submissions) for row in rows]
    return Page(items=items, page=page, per_page=per_page, total=total)


@router.post("/users/{user_id}/disable")
def disable(user_id: Id, body: ReasonIn, who: CallerDep, db: DBDep) -> DisabledOut:
    """Disable an account (a reason is required, and its owner is told it): it cannot log in
    or use its tokens, its sessions end, its queued and running submissions are cancelled."""
    admin = admin_of(who)
    user = accounts.get_user(db, user_id=user_id)
    cancelled = disable_account(db, user=user, by=admin, reason=body.reason)
    db.commit()
    return DisabledOut(**_out(db, user).model_dump(), cancelled=cancelled)


@router.post("/users/{user_id}/enable")
def enable(user_id: Id, body: ReasonIn, who: CallerDep, db: DBDep) -> AdminUserOut:
    """Let a disabled account log in and use its tokens again (admins)."""
    admin = admin_of(who)
    user = accounts.get_user(db, user_id=user_id)
    accounts.enable_user(db, user=user, by=admin, reason=body.reason)
    db.commit()
    return _out(db, user)


@router.post("/users/{user_id}/verify")
def verify(user_id: Id, admin: AdminDep, db: DBDep) -> AdminUserOut:
    """Mark the account's address verified (admins)."""
    user = accounts.get_user(db, user_id=user_id)
    accounts.mark_verified(db, user=user, by=admin)
    db.commit()
    return _out(db, user)


@router.put("/users/{user_id}/admin")
def grant_admin(user_id: Id, admin: AdminDep, db: DBDep) -> AdminUserOut:
    """Make the account an administrator (admins; not one's own)."""
    user = accounts.get_user(db, user_id=user_id)
    accounts.set_admin(db, user=user, by=admin, admin=True)
    db.commit()
    return _out(db, user)


@router.delete("/users/{user_id}/admin")
def revoke_admin(user_id: Id, admin: AdminDep, db: DBDep) -> AdminUserOut:
    """Take the account's administrator rights away (admins; not one's own)."""
    user = accounts.get_user(db, user_id=user_id)
    accounts.set_admin(db, user=user, by=admin, admin=False)
    db.commit()
    return _out(db, user)
