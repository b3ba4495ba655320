"""Challenges and their phases (dev, test, ...), each with its own leaderboard."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import Boolean, Float, ForeignKey, Integer, String, Text, UniqueConstraint, false
from sqlalchemy.orm import Mapped, mapped_column, relationship

from server.models.base import Base, utcnow


class Challenge(Base):
    __tablename__ = "challenges"

    id: Mapped[int] = mapped_column(primary_key=True)
    slug: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    suite_yaml: Mapped[str] = mapped_column(Text)
    suite_hash: Mapped[str] = mapped_column(String(64))
    quota_per_day: Mapped[int] = mapped_column(Integer, default=5)
    quota_concurrent: Mapped[int] = mapped_column(Integer, default=1)
    team_mode: Mapped[bool] = mapped_column(Boolean, default=False)
    """Quotas and leaderboard rows count per team instead of per user (docs/server.md, Teams)."""
    verification: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    """The suite's verification as it was loaded: `{"report": ... | null, "problems": [...]}`
    (server/challenges/verification.py); null for a challenge loaded before it was kept."""
    track_of: Mapped[int | None] = mapped_column(Integer, index=True)
    """The head of the group of tracks this challenge is a track of; None: it is a head (of
    its tracks, if any) or alone (docs/server.md, Tracks). No foreign key: SQLite adds one only
    by rebuilding `challenges` (alembic 0015); a track whose head is gone stands alone."""
    track: Mapped[str | None] = mapped_column(String(32))
    """The track's name within its group ("state", "visual"); None: its slug."""
    quota_shared: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    """On a group's head: its tracks' submissions count against one quota, the head's."""
    evaluator_image: Mapped[str | None] = mapped_column(String(512))
    """The evaluator image a Kubernetes Job of this challenge runs (``repo@sha256:...``: the
    project's evaluator with the suite's task packages), if the workers allow it; None: the
    workers' own (docs/deploy.md, Task packages)."""
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)

    phases: Mapped[list[Phase]] = relationship(
        back_populates="challenge",
        order_by="Phase.id",
        cascade="all, delete-orphan",
        lazy="raise",
    )


class Phase(Base):
    __tablename__ = "phases"
    __table_args__ = (UniqueConstraint("challenge_id", "name"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    challenge_id: Mapped[int] = mapped_column(ForeignKey("challenges.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(32))
    public_seeds: Mapped[bool] = mapped_column(Boolean)
    seed_commitment: Mapped[str] = mapped_column(String(64))
    opens_at: Mapped[datetime | None]
    closes_at: Mapped[datetime | None]
    leaderboard_version: Mapped[int] = mapped_column(Integer, default=0)
    """Bumped whenever any of the phase's leaderboard rows changes: the key of the snapshots'
    cache. Not `board_version`, which readers see."""
    board_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    """Which evaluation of the phase its board shows: moves when a re-evaluation is published
    (docs/server.md, Re-evaluation); `?version=N` reads an earlier one."""
    pending_board_version: Mapped[int | None] = mapped_column(Integer)
    """The version a re-evaluation in progress will publish; None when none is."""
    significance_level: Mapped[float] = mapped_column(Float, default=0.05)
    """The board's tie groups' family-wise level: the suite's phase's `significance_level`."""

    counts: Mapped[str] = mapped_column(String(8), default="best", server_default="best")
    """"best" or "last": which of a participant's submissions is their row (docs/server.md,
    Challenge rules); the suite's phase's `counts`."""
    final_choice: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    """Participants may mark one submission final; it is their row once it succeeded."""
    after_close: Mapped[str] = mapped_column(String(16), default="refuse", server_default="refuse")
    """"refuse" or "post_deadline": what becomes of a submission made after `closes_at`."""
    board: Mapped[str] = mapped_column(String(8), default="public", server_default="public")
    """"public" or "hidden": a hidden board is the organizers' (and each participant's own
    rows) until `published_at`."""
    published_at: Mapped[datetime | None]
    """When an organizer published the hidden board; None: not yet (or never hidden)."""

    challenge: Mapped[Challenge] = relationship(back_populates="phases", lazy="raise")

    def is_open(self, now: datetime) -> bool:
        return self.has_opened(now) and (self.closes_at is None or now < self.closes_at)

    def has_opened(self, now: datetime) -> bool:
        return self.opens_at is None or self.opens_at <= now

    def takes_late(self, now: datetime) -> bool:
        """Whether a submission now goes to the post-deadline board (the phase closed, and its
        organizers chose to take late ones)."""
        closed = self.closes_at is not None and self.closes_at <= now
        return closed and self.after_close == "post_deadline"

    def board_shown_to_all(self) -> bool:
        """Whether everyone sees the whole board (it is public, or published)."""
        return self.board != "hidden" or self.published_at is not None
