"""Audit: every organizer action leaves a record of who did what to whom, and why.

A domain that acts for an organizer calls `record` inside the transaction that makes the
change, so a change and its record commit together or not at all. Records are only ever added;
`records` reads them newest first for the console (docs/server.md, Audit).
"""

from __future__ import annotations

import getpass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.kit.errors import Invalid
from server.models import AuditRecord, User

REASON_MAX = 2000
"""The longest reason kept (the columns that hold one are this wide)."""


def reason_of(text: str | None, *, required: bool) -> str:
    """`text` as a reason: stripped, at most `REASON_MAX` characters, and present where the
    action needs one (hiding, disqualifying, disabling: whoever it affects is told why)."""
    reason = (text or "").strip()
    if required and not reason:
        raise Invalid("say why: a reason is required", fields={"reason": "required"})
    if len(reason) > REASON_MAX:
        too_long = f"at most {REASON_MAX} characters"
        raise Invalid(
            f"the reason is longer than {REASON_MAX} characters", fields={"reason": too_long}
        )
    return reason


def command_line_actor() -> str:
    """Who acts through `manieval` on the server's host: the login running it."""
    try:
        login = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (a bare container)
        login = "unknown"
    return f"cli:{login}"[:64]


def record(
    db: Session,
    *,
    by: User | None,
    action: str,
    target_kind: str,
    target_id: int | None,
    challenge_id: int | None = None,
    reason: str = "",
    detail: dict[str, Any] | None = None,
) -> AuditRecord:
    """Add the record of `action` to `db`'s transaction; `by` None: the command line."""
    entry = AuditRecord(
        actor_id=by.id if by is not None else None,
        actor=by.username if by is not None else command_line_actor(),
        action=action,
        target_kind=target_kind,
        target_id=target_id,
        challenge_id=challenge_id,
        reason=reason,
        detail=detail,
    )
    db.add(entry)
    return entry


def records(
    db: Session,
    *,
    challenge_id: int | None = None,
    action: str | None = None,
    target_kind: str | None = None,
    target_id: int | None = None,
    before_id: int | None = None,
    limit: int = 50,
) -> list[AuditRecord]:
    """The newest `limit` records matching every filter given, older than `before_id` if set
    (the next page starts below the last id shown)."""
    query = select(AuditRecord).order_by(AuditRecord.id.desc()).limit(limit)
    if challenge_id is not None:
        query = query.where(AuditRecord.challenge_id == challenge_id)
    if action is not None:
        query = query.where(AuditRecord.action == action)
    if target_kind is not None:
        query = query.where(AuditRecord.target_kind == target_kind)
    if target_id is not None:
        query = query.where(AuditRecord.target_id == target_id)
    if before_id is not None:
        query = query.where(AuditRecord.id < before_id)
    return list(db.scalars(query))
