"""Response bodies of the challenges API: a challenge, its phases, tasks, conditions, quota."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field

from evaluator.verification import VerificationReport


class PhaseOut(BaseModel):
    name: str
    description: str
    public_seeds: bool
    seed_commitment: str
    opens_at: datetime | None
    closes_at: datetime | None
    open: bool
    counts: Literal["best", "last"] = Field(
        default="best", description="which of a participant's submissions is their row"
    )
    final_choice: bool = Field(
        default=False, description="participants may mark one submission final"
    )
    after_close: Literal["refuse", "post_deadline"] = Field(
        default="refuse", description="what a submission after the close gets"
    )
    board: Literal["public", "hidden"] = Field(
        default="public", description="hidden: each participant sees only their own rows"
    )
    published_at: datetime | None = Field(
        default=None, description="when a hidden board was published to everyone"
    )


class TaskOut(BaseModel):
    env_id: str
    episodes: int
    max_episode_steps: int
    obs_mode: str
    control_mode: str


class ConditionOut(BaseModel):
    name: str
    kind: str


class QuotaOut(BaseModel):
    per_day_used: int
    per_day_limit: int
    concurrent_used: int
    concurrent_limit: int
    resets_at: datetime | None
    team: str | None = Field(
        default=None, description="The team whose members share this quota (team mode)."
    )
    shared_by: int = Field(
        default=1, description="How many tracks' submissions count against this quota."
    )
    quota_of: str = Field(
        default="", description="The challenge whose quota it is (a group's head when shared)."
    )


class TrackOut(BaseModel):
    name: str = Field(description="The track's name within its group")
    slug: str = Field(description="The track's challenge: its boards, submissions and phases")
    title: str


class VerificationOut(BaseModel):
    passed: bool = Field(description="The suite's report passed its thresholds when loaded.")
    problems: list[str] = Field(description="Why it did not (empty: it passed).")
    report: VerificationReport | None = Field(
        description="The report of `manieval challenge verify` (docs/verification.md); null: none."
    )


class ChallengeSummary(BaseModel):
    slug: str
    title: str
    description: str
    phases: list[PhaseOut]


class ChallengeOut(ChallengeSummary):
    suite_hash: str
    tasks: list[TaskOut]
    conditions: list[ConditionOut]
    quota_per_day: int
    quota_concurrent: int
    team_mode: bool = Field(
        default=False,
        description="Quotas and leaderboard rows count per team instead of per user.",
    )
    my_quota: QuotaOut | None
    verification: VerificationOut | None = Field(
        default=None,
        description="The suite's verification as loaded; null for a challenge loaded before "
        "verification was kept.",
    )
    track: str = Field(default="", description="This challenge's name within its group")
    tracks: list[TrackOut] = Field(
        default_factory=list,
        description="Its group's tracks, the head first (just itself when it has none)",
    )
    quota_shared: bool = Field(
        default=False, description="The group's tracks draw on one quota, the head's"
    )
    evaluator_image: str | None = Field(
        default=None,
        description="The evaluator image its Kubernetes Jobs run, pinned by digest (admins "
        "only; null for others, and where the workers' own runs it)",
    )
