"""Request and response bodies of the public API (``/api/v1``)."""

from __future__ import annotations

from datetime import datetime
from typing import Generic, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from server.models import State

T = TypeVar("T")


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=False)


class Page(BaseModel, Generic[T]):
    items: list[T]
    page: int
    per_page: int
    total: int


class RegisterIn(_In):
    username: str = Field(max_length=64)
    email: str = Field(max_length=320)
    password: str = Field(max_length=1024)


class LoginIn(_In):
    login: str = Field(max_length=320, description="username or email")
    password: str = Field(max_length=1024)


class TokenLoginIn(LoginIn):
    name: str = Field(default="cli", max_length=64)


class UserOut(BaseModel):
    id: int
    username: str
    email: str
    is_admin: bool
    created_at: datetime


class SessionOut(BaseModel):
    user: UserOut
    csrf_token: str


class TokenIn(_In):
    name: str = Field(max_length=64)


class TokenOut(BaseModel):
    id: int
    name: str
    prefix: str
    created_at: datetime
    last_used_at: datetime | None
    revoked_at: datetime | None


class NewTokenOut(TokenOut):
    token: str = Field(description="shown once: store it now")


class PhaseOut(BaseModel):
    name: str
    description: str
    public_seeds: bool
    seed_commitment: str
    opens_at: datetime | None
    closes_at: datetime | None
    open: bool


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
    my_quota: QuotaOut | None


class SubmitIn(_In):
    challenge: str = Field(max_length=64)
    phase: str = Field(default="dev", max_length=32)
    image: str = Field(max_length=512)
    description: str = Field(default="", max_length=2000)
    public: bool = True


class SubmissionPatch(_In):
    public: bool | None = None
    hidden: bool | None = Field(default=None, description="admins only")
    baseline: bool | None = Field(default=None, description="admins only")
    description: str | None = Field(default=None, max_length=2000)


class TransitionOut(BaseModel):
    attempt: int
    from_state: State | None
    to_state: State
    reason: str
    at: datetime


class TaskResultOut(BaseModel):
    condition: str
    env_id: str
    episodes: int
    successes: int
    success_rate: float
    ci_low: float
    ci_high: float
    mean_steps: float


class SubmissionOut(BaseModel):
    id: int
    username: str
    challenge: str
    phase: str
    image: str
    pinned_image: str
    description: str
    public: bool
    hidden: bool
    baseline: bool
    state: State
    reason: str
    attempt: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    score: float | None
    progress: dict[str, object] | None


class SubmissionDetail(SubmissionOut):
    transitions: list[TransitionOut]
    tasks: list[TaskResultOut]
    conditions: dict[str, float]


class EpisodeOut(BaseModel):
    condition: str
    env_id: str
    index: int
    seed: int | None = Field(description="null in phases whose seeds are secret")
    success_once: bool
    success_at_end: bool
    steps: int
    episode_return: float
    wall_time_s: float
    invalid_actions: int
    clipped_actions: int
    failure: str | None


class LogsOut(BaseModel):
    submission_id: int
    attempt: int
    log_tail: str


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


class Ok(BaseModel):
    ok: bool = True


# Internal (worker) API ------------------------------------------------------------------------


class StateReport(_In):
    state: State
    reason: str = Field(max_length=2000)


class ProgressReport(_In):
    progress: dict[str, int | float | str]


class FinalReport(_In):
    state: State
    reason: str = Field(max_length=2000)
    result: dict[str, object] | None = None
    log_tail: str = Field(default="", max_length=1 << 20)


class ReportOut(BaseModel):
    applied: bool
    state: State
