"""The versioned result document of an evaluation, and how it is aggregated from episodes."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from evaluator.stats import wilson_interval

# 1.1: `success_at_end` is null when the suite does not measure it (episodes that stop at the
# first success); `budget` and each episode's `policy_time_s` say how much time the policy took.
# 1.2: `provenance` says what produced the numbers (docs/metrics.md, Provenance).
# 1.3: the provenance's `packages`, the suite's task packages with their versions.
# A 1.0 or 1.1 document still reads as one, with no provenance; a 1.2 one with no packages.
RESULT_SCHEMA_VERSION: Literal["1.3"] = "1.3"

FailureKind = Literal[
    "invalid_action",
    "policy_error",
    "policy_crashed",
    "policy_timeout",
    "protocol_error",
    "budget_exhausted",
    "not_run",
    # A sandboxed policy ran out of a resource limit and was stopped (evaluator/sandbox.py).
    "memory_limit",
    "process_limit",
    "file_size_limit",
]


class _Doc(BaseModel):
    model_config = ConfigDict(extra="forbid")


class EpisodeResult(_Doc):
    """One episode: the seed it ran with and what happened (docs/metrics.md)."""

    index: int = Field(ge=0)
    seed: int = Field(ge=0)
    success_once: bool
    success_at_end: bool | None = Field(
        description="Success at the last step; null when the suite ends episodes at the first "
        "success, where it would only repeat success_once"
    )
    steps: int = Field(ge=0)
    episode_return: float
    wall_time_s: float = Field(ge=0)
    policy_time_s: float = Field(
        default=0.0, ge=0, description="Time the policy took answering reset and act"
    )
    invalid_actions: int = Field(default=0, ge=0)
    clipped_actions: int = Field(default=0, ge=0)
    failure: FailureKind | None = None
    failure_reason: str | None = None


class TaskResult(_Doc):
    """One task under one condition: success rate with its Wilson 95% interval."""

    env_id: str
    episodes_planned: int = Field(ge=0)
    successes: int = Field(ge=0)
    success_rate: float = Field(ge=0, le=1)
    ci_low: float = Field(ge=0, le=1)
    ci_high: float = Field(ge=0, le=1)
    success_at_end_rate: float | None = Field(ge=0, le=1)
    mean_steps: float = Field(ge=0)
    mean_return: float
    episodes: list[EpisodeResult]


class ConditionResult(_Doc):
    """All tasks under one evaluation condition; `score` is the mean task success rate."""

    name: str
    params: dict[str, object]
    score: float = Field(ge=0, le=1)
    tasks: list[TaskResult]


class Abort(_Doc):
    """Why an evaluation stopped before running every episode."""

    kind: FailureKind
    reason: str
    log_tail: str = ""


class BudgetUse(_Doc):
    """The policy's time budget and how much of it the policy used, over all workers."""

    budget_s: float = Field(gt=0)
    used_s: float = Field(
        ge=0, description="Time the evaluator waited for the policy's answers to reset and act"
    )


class Video(_Doc):
    env_id: str
    condition: str
    episode: int
    path: str


class Versions(_Doc):
    manieval: str
    mani_skill: str
    sapien: str
    torch: str
    python: str


class SuiteRef(_Doc):
    name: str
    version: int
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")


class Environment(_Doc):
    """What decides the scores besides the policy and the seeds, in the form the service
    compares with the environment it would evaluate in now (`evaluator.provenance`)."""

    mani_skill: str | None
    sapien: str | None
    torch: str | None = Field(description="Without its local label: 2.13.0 for 2.13.0+cpu")
    numpy: str | None
    sim_backend: str = Field(description="The tasks' simulation backends, joined by '+'")
    render_backend: str = Field(description="The renderers those backends use, joined by '+'")
    suite_sha256: str = Field(pattern=r"^[0-9a-f]{64}$")


class Machine(_Doc):
    """Where episodes ran: the CPU's model name and the GPUs the evaluator saw (null: none)."""

    cpu: str | None
    gpu: str | None


class EvaluatorBuild(_Doc):
    """The evaluator's code: ManiEval's version, its git commit when run from a checkout, and
    the evaluator image (Kubernetes) as the Job names it."""

    manieval: str
    commit: str | None = None
    image: str | None = None


class ScoringSettings(_Doc):
    """The suite's settings that change what a policy scores (all of them in the suite's hash)."""

    ignore_terminations: bool
    control_mode: dict[str, str] = Field(description="Each task's controller")
    max_episode_steps: dict[str, int] = Field(description="Each task's step limit")
    action_chunk_max: int = Field(ge=1, description="The longest action chunk taken")
    action_chunk_execute: int = Field(ge=1, description="Actions of a chunk executed")


class Provenance(_Doc):
    """What produced a result (schema 1.2): see docs/metrics.md, Provenance."""

    environment: Environment
    suite_version: int
    evaluator: EvaluatorBuild
    policy_image: str | None = Field(
        description="The policy's image, pinned by digest; null for a policy that is no image"
    )
    machines: list[Machine] = Field(
        min_length=1, description="The distinct machines the shards ran on, in shard order"
    )
    settings: ScoringSettings
    packages: dict[str, str] = Field(
        default={},
        description="The suite's task packages with the version the evaluator imported "
        "(schema 1.3; empty: the suite names none)",
    )
    shards: int = Field(default=1, ge=1)
    shard_differences: dict[str, list[str | None]] = Field(
        default={},
        description="Environment fields on which the shards differed, with each shard's value "
        "(empty: every shard ran in `environment`)",
    )


class EvaluationResult(_Doc):
    """What an evaluation produced: the document the server stores and the CLI prints."""

    schema_version: Literal["1.0", "1.1", "1.2", "1.3"] = RESULT_SCHEMA_VERSION
    suite: SuiteRef
    phase: str
    policy: str
    versions: Versions
    provenance: Provenance | None = None
    started_at: datetime
    finished_at: datetime
    status: Literal["completed", "aborted"]
    abort: Abort | None = None
    budget: BudgetUse | None = None
    score: float = Field(ge=0, le=1, description="Mean task success rate, first condition")
    conditions: list[ConditionResult]
    videos: list[Video] = []


TIMINGS = frozenset({"wall_time_s", "policy_time_s"})
"""Fields of an episode's record that measure time: no two runs share them."""


def episode_records(result: EvaluationResult) -> list[dict[str, object]]:
    """Every episode's record except its timings, which no two runs share: two evaluations of a
    deterministic policy on the same plan give equal lists, however many workers ran them."""
    return [
        {"condition": c.name, "task": t.env_id, **e.model_dump(exclude=set(TIMINGS))}
        for c in result.conditions
        for t in c.tasks
        for e in t.episodes
    ]


def ran(episode: EpisodeResult) -> bool:
    """Whether the episode ran, in whole or in part: those planned that an evaluation stopped
    before (or a policy that never connected never reached) are `not_run`."""
    return episode.failure != "not_run"


def aggregate_task(env_id: str, planned: int, episodes: list[EpisodeResult]) -> TaskResult:
    """Summarise a task's episodes; episodes planned but not run count as failures of the
    rate (a completed evaluation has none), while the means are of the episodes that ran.

    The success-at-end rate is null when the episodes do not measure it (they stopped at the
    first success); a suite either measures it in every episode or in none.
    """
    successes = sum(e.success_once for e in episodes)
    low, high = wilson_interval(successes, planned)
    done = [e for e in episodes if ran(e)]
    count = max(len(done), 1)
    at_end_measured = all(e.success_at_end is not None for e in episodes)
    at_end = sum(bool(e.success_at_end) for e in episodes)
    return TaskResult(
        env_id=env_id,
        episodes_planned=planned,
        successes=successes,
        success_rate=successes / planned if planned else 0.0,
        ci_low=low,
        ci_high=high,
        success_at_end_rate=(at_end / planned if planned else 0.0) if at_end_measured else None,
        mean_steps=sum(e.steps for e in done) / count,
        mean_return=sum(e.episode_return for e in done) / count,
        episodes=episodes,
    )


def condition_score(tasks: list[TaskResult]) -> float:
    """Mean of task success rates (the suite score)."""
    return mean_success_rate([t.success_rate for t in tasks])


def mean_success_rate(rates: Sequence[float]) -> float:
    """A condition's score: the mean of its tasks' success rates (0 without tasks)."""
    return sum(rates) / len(rates) if rates else 0.0


def condition_means(rates: Iterable[tuple[str, float]]) -> dict[str, float]:
    """Each condition's score, from its tasks' (condition, success rate) in document order."""
    by_condition: dict[str, list[float]] = {}
    for condition, rate in rates:
        by_condition.setdefault(condition, []).append(rate)
    return {name: mean_success_rate(found) for name, found in by_condition.items()}
