"""The stored leaderboard: one precomputed row per (phase, user), per (phase, team) in team
mode, and per baseline."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import Boolean, Float, ForeignKey, Index, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from server.models.base import Base


class LeaderboardEntry(Base):
    """One row of a phase's leaderboard: a user's (or in team mode a team's) best public
    succeeded submission, or a submission an admin flagged as a baseline (each baseline is its
    own row).

    Maintained by ``server.leaderboard.service.refresh`` whenever one of its inputs changes, so that
    reading a leaderboard is one indexed range scan however many submissions exist.
    """

    __tablename__ = "leaderboard_entries"
    __table_args__ = (
        # owner_key is the user id for regular rows and NULL for baselines: at most one
        # regular row per user and phase, any number of baselines.
        UniqueConstraint("phase_id", "board_version", "owner_key"),
        # team_id is the team for a team's row (team mode) and NULL otherwise: at most one row
        # per team and phase. A separate key space: a team id never collides with a user id.
        UniqueConstraint(
            "phase_id", "board_version", "team_id", name="uq_leaderboard_entries_phase_team"
        ),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    phase_id: Mapped[int] = mapped_column(ForeignKey("phases.id", ondelete="CASCADE"))
    board_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    """The phase's board version this row is on (its submission's)."""
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), unique=True
    )
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    owner_key: Mapped[int | None] = mapped_column(Integer)
    """The user for a user's row; NULL for a baseline and for a team's row."""
    team_id: Mapped[int | None] = mapped_column(
        ForeignKey("teams.id", ondelete="CASCADE"), index=True
    )
    """The team for a team's row (team mode); NULL otherwise."""
    team_name: Mapped[str | None] = mapped_column(String(32))
    team_display_name: Mapped[str | None] = mapped_column(String(64))
    baseline: Mapped[bool] = mapped_column(Boolean)
    score: Mapped[float] = mapped_column(Float)
    submitted_at: Mapped[datetime]
    username: Mapped[str] = mapped_column(String(32))
    """Who submitted the row's submission (for a team's row: the member who did)."""
    method: Mapped[str | None] = mapped_column(String(100))
    paper_url: Mapped[str | None] = mapped_column(String(500))
    code_url: Mapped[str | None] = mapped_column(String(500))
    summary: Mapped[dict[str, Any]]
    """Per-condition scores and per-task success with intervals, as the leaderboard shows."""
    outcomes: Mapped[dict[str, Any] | None]
    """The first condition's episode outcomes, packed (`evaluator.paired.PackedOutcomes`):
    what the board's tie groups pair. None in rows stored before it was, and for a submission
    with no episodes."""


Index(
    "ix_leaderboard_rank",
    LeaderboardEntry.phase_id,
    LeaderboardEntry.board_version,
    LeaderboardEntry.score.desc(),
    LeaderboardEntry.submitted_at,
    LeaderboardEntry.id,
)
