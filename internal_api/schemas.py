"""What travels over ``/internal/v1``: claims, the evaluation a worker is handed, its reports.

Every report names its (submission, attempt) in the URL and is idempotent: the server applies
it once, answers an identical repeat with the same outcome, and refuses a report about an
attempt that is no longer the submission's current one (409), so a late worker cannot
overwrite a re-run.
"""

from __future__ import annotations

import enum
import re

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from evaluator.plan import EvaluationPlan
from evaluator.results import EvaluationResult

REASON_LIMIT = 2000
LOG_TAIL_LIMIT = 64 * 1024
Progress = dict[str, int | float | str]
IMAGE_DIGEST = r"sha256:[0-9a-f]{64}"
PINNED_IMAGE = re.compile(rf"[A-Za-z0-9][A-Za-z0-9._:/-]*@{IMAGE_DIGEST}")
"""An image reference pinned to exactly one manifest, ``repo@sha256:<hex>`` (match it whole)."""


class State(enum.StrEnum):
    """Where a submission's current attempt stands."""

    QUEUED = "queued"
    LAUNCHING = "launching"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"  # the policy's fault
    ERROR = "error"  # ours
    CANCELLED = "cancelled"
    TIMED_OUT = "timed_out"

    @property
    def final(self) -> bool:
        return self in FINAL_STATES


FINAL_STATES = frozenset(
    {State.SUCCEEDED, State.FAILED, State.ERROR, State.CANCELLED, State.TIMED_OUT}
)
ACTIVE_STATES = frozenset({State.QUEUED, State.LAUNCHING, State.RUNNING})


class ErrorCause(enum.StrEnum):
    """Who caused an `error` a worker reports, where the server acts on it."""

    CLUSTER = "cluster"
    """The cluster stopped the evaluation (evicted, preempted, unschedulable, refused by a
    quota, a node lost): no quota used, and the submission runs again once."""
    CONFIGURATION = "configuration"
    """The operator's configuration cannot run it (a challenge's evaluator image the workers
    are not allowed to run): no quota used, and not run again by itself, since it would fail
    the same way until the operator changes the configuration."""


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ClaimIn(_Body):
    worker: str = Field(min_length=1, max_length=200, pattern=r"^[\x21-\x7e]+$")
    """Who claims (printable ASCII, no spaces): recorded with the attempt, so that a worker
    that restarts can say which of its attempts died with it."""


class Assignment(BaseModel):
    """A claimed attempt, with everything a worker needs to run it and nothing secret."""

    submission_id: int
    attempt: int
    image: str
    """The pinned image reference (``repo@sha256:...``), or ``local:NAME``."""
    plan: EvaluationPlan
    """The evaluation with its concrete seeds: the worker never holds the seed secret."""
    suite_yaml: str
    """The suite's text, for an evaluator that runs elsewhere (a Kubernetes Job)."""
    shards: int = Field(ge=1)
    """Into how many pods a Kubernetes Job may split the episodes."""
    evaluator_image: str | None = None
    """The challenge's own evaluator image (``repo@sha256:...``, one with its task packages),
    which a Kubernetes Job runs the evaluator on if the worker allows it; None: the worker's
    own (``MANIEVAL_EVALUATOR_IMAGE``). Executors that evaluate in the worker ignore it."""


class RunningReport(_Body):
    reason: str = Field(min_length=1, max_length=REASON_LIMIT)
    deadline_s: float = Field(gt=0, le=30 * 86400)
    """Seconds from now after which the server times the attempt out."""


class ProgressReport(_Body):
    progress: Progress | None = None
    """None: a heartbeat only (the last progress stays)."""


class FinalReport(_Body):
    state: State
    reason: str = Field(min_length=1, max_length=REASON_LIMIT)
    result: EvaluationResult | None = None
    log_tail: str = Field(default="", max_length=LOG_TAIL_LIMIT)
    cause: ErrorCause | None = None
    """Set only with `error`: who caused it, when not the evaluation itself."""

    @field_validator("state")
    @classmethod
    def _final(cls, state: State) -> State:
        if not state.final:
            raise ValueError(f"{state.value} is not a final state")
        return state

    @model_validator(mode="after")
    def _cause_only_with_error(self) -> FinalReport:
        if self.cause is not None and self.state != State.ERROR:
            raise ValueError(f"a cause goes only with error, not {self.state.value}")
        return self


class ReportOut(BaseModel):
    applied: bool
    """False: the report no longer applies (the attempt was cancelled or ended elsewhere)."""
    state: State
    """The submission's state after the report."""


class AttemptRef(BaseModel):
    submission_id: int
    attempt: int


class Silent(BaseModel):
    """Running attempts whose worker has not reported within the heartbeat timeout."""

    attempts: list[AttemptRef]


class ReconcileOut(BaseModel):
    """What one reconciling pass did, and which attempts are still active."""

    timed_out: list[int] = Field(default_factory=list)
    lost: list[int] = Field(default_factory=list)
    requeued: list[int] = Field(default_factory=list)
    woken: int = 0
    active: list[AttemptRef] = Field(default_factory=list)


class RestartOut(BaseModel):
    """The attempts a restarted worker had in flight, now ended."""

    ended: list[int]
