"""Response bodies of the leaderboard API."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel

from server.kit.schemas import Page


class LeaderboardRowOut(BaseModel):
    rank: int | None
    username: str
    submission_id: int
    baseline: bool
    score: float
    submitted_at: datetime
    conditions: dict[str, float]
    tasks: dict[str, dict[str, float]]


class LeaderboardOut(Page[LeaderboardRowOut]):
    challenge: str
    phase: str
