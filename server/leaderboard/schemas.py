"""Response bodies of the leaderboard API."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from server.kit.schemas import Page


class LeaderboardRowOut(BaseModel):
    rank: int | None = Field(
        description="1 for the best score; null for a baseline or a disqualified row (unranked)."
    )
    username: str = Field(description="Who submitted (for a team's row: the member who did).")
    team: str | None = Field(
        default=None,
        description="The team's name, for a team's row (a challenge with team mode on); its "
        "page is /teams/{team}.",
    )
    team_display_name: str | None = Field(default=None, description="The team's display name.")
    method: str | None = Field(default=None, description="The submission's method name.")
    paper_url: str | None = Field(default=None, description="An http(s) link to its paper.")
    code_url: str | None = Field(default=None, description="An http(s) link to its code.")
    submission_id: int
    baseline: bool
    score: float
    submitted_at: datetime
    conditions: dict[str, float] = Field(
        description="Mean success rate per condition, in the suite's order."
    )
    tasks: dict[str, dict[str, float]] = Field(
        description="Success rate and its 95% interval per task (first condition), in the "
        "suite's order."
    )
    score_ci_low: float | None = Field(
        default=None,
        description="The score's 95% Wilson interval over the first condition's episodes "
        "pooled; null only for a submission with no results.",
    )
    score_ci_high: float | None = Field(default=None, description="The interval's upper end.")
    environment_differs: list[str] = Field(
        default=[],
        description="What of the entry's evaluation environment differs from the one the "
        "service would evaluate in now: any of mani_skill, sapien, torch, numpy, sim_backend, "
        "render_backend, suite_sha256 (docs/metrics.md, Provenance); empty: the same, or not "
        "known.",
    )
    disqualified: str | None = Field(
        default=None,
        description="Why the organizers disqualified it: such a row stays on the board, "
        "unranked, after the ranked rows; null: not disqualified.",
    )
    tied: bool = Field(
        default=False,
        description="In the tie group of the ranked row above: McNemar's exact test on their "
        "paired episodes does not separate them (docs/metrics.md, Paired significance).",
    )
    tie_group: int | None = Field(
        default=None,
        description="1, 2, ... down the board: consecutive ranked rows that the paired test, "
        "Holm-corrected over the board's adjacent comparisons at the phase's "
        "`significance_level`, does not separate share a group (docs/metrics.md, Paired "
        "significance); null for a baseline.",
    )


class LeaderboardOut(Page[LeaderboardRowOut]):
    challenge: str
    phase: str
    tasks: list[str] = Field(description="The suite's tasks, in its order: the column order.")
    conditions: list[str] = Field(description="The suite's conditions, in its order.")


class LateRowOut(BaseModel):
    rank: int | None = Field(
        description="1 for the best score; null on a hidden board's own rows (not published)"
    )
    username: str
    submission_id: int
    score: float
    submitted_at: datetime


class PostDeadlineOut(BaseModel):
    challenge: str
    phase: str
    items: list[LateRowOut] = Field(
        description="Each participant's row among what they submitted after the phase closed, "
        "by the phase's `counts` rule; never part of the official board."
    )
