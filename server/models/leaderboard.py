"""The stored leaderboard: one precomputed row per (phase, user) and per baseline."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import Boolean, Float, ForeignKey, Index, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from server.models.base import Base


class LeaderboardEntry(Base):
    """One row of a phase's leaderboard: a user's best public succeeded submission, or a
    submission an admin flagged as a baseline (each baseline is its own row).

    Maintained by ``server.leaderboard.service.refresh`` whenever one of its inputs changes, so that
    reading a leaderboard is one indexed range scan however many submissions exist.
    """

    __tablename__ = "leaderboard_entries"
    __table_args__ = (
        # owner_key is the user id for regular rows and NULL for baselines: at most one
        # regular row per user and phase, any number of baselines.
        UniqueConstraint("phase_id", "owner_key"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    phase_id: Mapped[int] = mapped_column(ForeignKey("phases.id", ondelete="CASCADE"))
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), unique=True
    )
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    owner_key: Mapped[int | None] = mapped_column(Integer)
    baseline: Mapped[bool] = mapped_column(Boolean)
    score: Mapped[float] = mapped_column(Float)
    submitted_at: Mapped[datetime]
    username: Mapped[str] = mapped_column(String(32))
    summary: Mapped[dict[str, Any]]
    """Per-condition scores and per-task success with intervals, as the leaderboard shows."""


Index(
    "ix_leaderboard_rank",
    LeaderboardEntry.phase_id,
    LeaderboardEntry.score.desc(),
    LeaderboardEntry.submitted_at,
    LeaderboardEntry.id,
)
