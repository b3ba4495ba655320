"""The audit log as organizers read it, through the API and `manieval admin audit`: records
newest first, each with the slug of the challenge it concerns, a page at a time."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server import audit
from server.challenges.service import get_challenge
from server.models import AuditRecord, Challenge


@dataclass(frozen=True)
class AuditEntry:
    record: AuditRecord
    challenge: str | None
    """The slug of the challenge it concerns (None: none, or the challenge was deleted)."""


@dataclass(frozen=True)
class AuditListing:
    entries: list[AuditEntry]
    next_before_id: int | None
    """Where the next (older) page starts (`before_id`); None: this is the last."""


def audit_listing(
    db: DB,
    *,
    challenge: str | None = None,
    action: str | None = None,
    before_id: int | None = None,
    limit: int = 50,
) -> AuditListing:
    """The newest `limit` records, of a challenge (by slug; NotFound for none) and an action
    if given, older than `before_id` if given."""
    found = get_challenge(db, slug=challenge) if challenge is not None else None
    records = audit.records(
        db,
        challenge_id=found.id if found is not None else None,
        action=action,
        before_id=before_id,
        limit=limit + 1,  # one more: whether an older page exists
    )
    shown = records[:limit]
    ids = {r.challenge_id for r in shown if r.challenge_id is not None}
    slugs: dict[int, str] = {}
    if ids:
        named = select(Challenge.id, Challenge.slug).where(Challenge.id.in_(ids))
        slugs = dict(db.execute(named).all())
    entries = [
        AuditEntry(r, slugs.get(r.challenge_id) if r.challenge_id is not None else None)
        for r in shown
    ]
    more = len(records) > limit
    return AuditListing(entries=entries, next_before_id=shown[-1].id if more else None)
