"""A concrete evaluation plan: what the evaluator runs, with seeds already resolved."""

from __future__ import annotations

from collections.abc import Sequence

from pydantic import BaseModel, ConfigDict, Field

from evaluator.results import SuiteRef
from evaluator.suite import Condition, Limits, Suite, SuiteError, phase_seeds


class TaskRun(BaseModel):
    """One task under one condition, on concrete seeds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    env_id: str
    obs_mode: str
    control_mode: str
    sim_backend: str
    max_episode_steps: int = Field(ge=1)
    condition: Condition
    seeds: tuple[int, ...]


class EvaluationPlan(BaseModel):
    """Everything the evaluator needs; it never sees a suite's seed secret."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    suite: SuiteRef
    phase: str
    limits: Limits
    runs: tuple[TaskRun, ...]
    ignore_terminations: bool = False
    record_video: bool = False

    def episode_count(self) -> int:
        """Episodes in the whole plan."""
        return sum(len(run.seeds) for run in self.runs)


def build_plan(
    suite: Suite,
    phase: str,
    *,
    tasks: Sequence[str] | None = None,
    conditions: Sequence[str] | None = None,
    episodes: int | None = None,
    secret: bytes | None = None,
    record_video: bool = False,
) -> EvaluationPlan:
    """Resolve a suite, a phase and optional narrowing into concrete task runs."""
    if episodes is not None and episodes < 1:
        raise SuiteError("episodes must be at least 1")
    selected_tasks = [suite.task(t) for t in tasks] if tasks else list(suite.tasks)
    selected_conditions = (
        [suite.condition(c) for c in conditions] if conditions else list(suite.conditions)
    )
    suite.phase(phase)
    runs = []
    for condition in selected_conditions:
        for task in selected_tasks:
            count = episodes if episodes is not None else task.episodes
            seeds = phase_seeds(suite, phase, task.env_id, count, secret=secret)
            runs.append(
                TaskRun(
                    env_id=task.env_id,
                    obs_mode=task.obs_mode,
                    control_mode=task.control_mode,
                    sim_backend=task.sim_backend,
                    max_episode_steps=task.max_episode_steps,
                    condition=condition,
                    seeds=tuple(seeds),
                )
            )
    return EvaluationPlan(
        suite=SuiteRef(name=suite.name, version=suite.version, sha256=suite.sha256()),
        phase=phase,
        limits=suite.limits,
        runs=tuple(runs),
        ignore_terminations=suite.ignore_terminations,
        record_video=record_video,
    )
