"""Audit records: who did what to whom, and why, for every organizer action (docs/server.md,
Audit)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import ForeignKey, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from server.models.base import Base, utcnow


class AuditRecord(Base):
    """One organizer action, written in the transaction that makes it: no action stands
    without its record. Never updated or deleted by the service."""

    __tablename__ = "audit_records"

    id: Mapped[int] = mapped_column(primary_key=True)
    at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    actor_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), index=True
    )
    """The admin who acted on the web or through the API; None for the command line."""
    actor: Mapped[str] = mapped_column(String(64))
    """Who acted, as it read then: the admin's user name, or ``cli:LOGIN`` for `manieval`
    commands run on the server's host (they hold the database, not an account)."""
    action: Mapped[str] = mapped_column(String(64), index=True)
    """What was done, ``domain.verb``: ``submission.hide``, ``phase.close``, ``user.disable``."""
    target_kind: Mapped[str] = mapped_column(String(32))
    """What it was done to: ``submission``, ``phase``, ``challenge``, ``user``."""
    target_id: Mapped[int | None] = mapped_column(Integer)
    challenge_id: Mapped[int | None] = mapped_column(
        ForeignKey("challenges.id", ondelete="SET NULL"), index=True
    )
    """The challenge the action concerns, if any: a challenge's organizers read its records."""
    reason: Mapped[str] = mapped_column(String(2000), default="")
    detail: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    """What changed, where a reader needs it (the old and new value of a setting, the
    submissions a bulk re-run queued)."""
