"""Request and response bodies of the submissions API, and the reports of the internal
(worker) API."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from pydantic import BaseModel, Field

from evaluator.results import Provenance
from server.audit import REASON_MAX
from server.kit.schemas import InBody
from server.models import State
from server.submissions.method import METHOD_MAX, METHOD_PATTERN, URL_MAX, URL_PATTERN

_METHOD = "the method's name, shown on the leaderboard"
MethodName = Annotated[str, Field(json_schema_extra={"pattern": METHOD_PATTERN})]
"""Documents what `Method.checked` refuses (its check runs in the service, for forms too)."""
_PAPER = "an absolute http(s) link to the method's paper"
_CODE = "an absolute http(s) link to the method's code"


class SubmitIn(InBody):
    challenge: str = Field(max_length=64)
    track: str | None = Field(
        default=None,
        max_length=64,
        description="a track of the challenge's group, by name or slug (none: the challenge)",
    )
    phase: str = Field(default="dev", max_length=32)
    image: str = Field(max_length=512)
    description: str = Field(default="", max_length=2000)
    public: bool = True
    method: MethodName | None = Field(default=None, max_length=METHOD_MAX, description=_METHOD)
    paper_url: str | None = Field(
        default=None, max_length=URL_MAX, pattern=URL_PATTERN, description=_PAPER
    )
    code_url: str | None = Field(
        default=None, max_length=URL_MAX, pattern=URL_PATTERN, description=_CODE
    )


class SubmissionPatch(InBody):
    public: bool | None = None
    hidden: bool | None = Field(
        default=None, description="admins only; hiding takes a `reason` (POST .../hide)"
    )
    reason: str | None = Field(
        default=None,
        max_length=REASON_MAX,
        description="admins only: why it is hidden, which its owner is shown",
    )
    baseline: bool | None = Field(default=None, description="admins only")
    description: str | None = Field(default=None, max_length=2000)
    method: MethodName | None = Field(
        default=None, max_length=METHOD_MAX, description=_METHOD + '; "" removes it'
    )
    paper_url: str | None = Field(
        default=None,
        max_length=URL_MAX,
        pattern=URL_PATTERN,
        description=_PAPER + '; "" removes it',
    )
    code_url: str | None = Field(
        default=None, max_length=URL_MAX, pattern=URL_PATTERN, description=_CODE + '; "" removes it'
    )


class TransitionOut(BaseModel):
    attempt: int
    from_state: State | None
    to_state: State
    reason: str
    at: datetime


class TaskResultOut(BaseModel):
    condition: str
    env_id: str
    episodes: int = Field(description="episodes planned")
    episodes_ran: int = Field(
        description="episodes that ran, in whole or in part: fewer than planned when the "
        "evaluation ended part-way (failed, timed out, cancelled), 0 when none ran"
    )
    successes: int
    success_rate: float | None = Field(
        description="successes over the planned episodes; null unless every one of them ran"
    )
    ci_low: float | None = Field(description="Wilson 95% interval; null like success_rate")
    ci_high: float | None = Field(description="Wilson 95% interval; null like success_rate")
    mean_steps: float | None = Field(description="over the episodes that ran; null if none did")


class QueueOut(BaseModel):
    """Where a queued submission stands."""

    position: int = Field(ge=1, description="1: the next one a free worker claims")
    ahead: int = Field(ge=0, description="submissions claimed before this one")
    expected_start_s: float | None = Field(
        description="seconds until it is expected to start, from the evaluations running "
        "now and the challenges' recent evaluation times; null while unknown"
    )
    text: str = Field(description='in words: "3rd in the queue, about 4 min"')


class SubmissionOut(BaseModel):
    id: int
    username: str
    challenge: str
    phase: str
    image: str
    pinned_image: str
    description: str
    method: str | None
    paper_url: str | None
    code_url: str | None
    public: bool
    hidden: bool
    disqualified: bool = Field(
        default=False, description="on its board unranked, by the organizers' decision"
    )
    moderation_reason: str | None = Field(
        default=None, description="why the organizers hid or disqualified it"
    )
    baseline: bool
    state: State
    reason: str
    attempt: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    score: float | None
    progress: dict[str, object] | None
    final: bool = Field(default=False, description="its owner's final choice in its phase")
    post_deadline: bool = Field(
        default=False, description="made after its phase closed: on the post-deadline board"
    )
    queue: QueueOut | None = Field(
        default=None, description="while queued: its place and expected start"
    )


class SubmissionDetail(SubmissionOut):
    transitions: list[TransitionOut]
    tasks: list[TaskResultOut]
    conditions: dict[str, float] = Field(
        description="each condition's mean success rate over its tasks, for the conditions "
        "whose every planned episode ran"
    )
    provenance: Provenance | None = Field(
        default=None,
        description="what produced the current attempt's result: the evaluation environment, "
        "the evaluator, the policy's image, the machines and the settings that change scores "
        "(docs/metrics.md, Provenance); null without a result or for one recorded before "
        "result schema 1.2",
    )


class EpisodeOut(BaseModel):
    condition: str
    env_id: str
    index: int
    seed: int | None = Field(description="null in phases whose seeds are secret")
    success_once: bool
    success_at_end: bool | None
    """None: not measured (the suite stops an episode at its first success)."""
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


# An organizer's actions (server/submissions/admin_api.py) ---------------------------------


class ReasonIn(InBody):
    reason: str = Field(
        default="",
        max_length=REASON_MAX,
        description="why (at most 2000 characters): required to hide or disqualify, and shown "
        "to the submission's owner; optional to undo either or to re-run, kept in the audit log",
    )


class RerunStuckIn(ReasonIn):
    challenge: str | None = Field(
        default=None, max_length=64, description="only this challenge's (none: every one's)"
    )


class RerunStuckOut(BaseModel):
    requeued: list[int] = Field(description="the submissions queued again, as new attempts")


class ReevaluationOut(BaseModel):
    phase: str
    board_version: int = Field(description="the board version the re-evaluations count for")
    submissions: list[int] = Field(description="the re-evaluations' ids, in the board's order")


class AuditRecordOut(BaseModel):
    id: int
    at: datetime
    actor: str = Field(description="the admin's user name, or cli:LOGIN for a command")
    action: str = Field(description="domain.verb: submission.hide, phase.close, ...")
    target_kind: str
    target_id: int | None
    challenge: str | None = Field(description="the challenge it concerns, by slug")
    reason: str
    detail: dict[str, Any] | None


class AuditPage(BaseModel):
    items: list[AuditRecordOut] = Field(description="newest first")
    next_before_id: int | None = Field(
        description="pass as before_id for the next (older) page; null: no more"
    )
