"""Evaluate a plan: shard it over worker processes, merge their episodes into one result."""

from __future__ import annotations

import functools
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from evaluator.plan import EvaluationPlan
from evaluator.pool import can_start_processes, run_warm
from evaluator.provenance import installed_versions, local_provenance
from evaluator.results import (
    BudgetUse,
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    Provenance,
    Versions,
    aggregate_task,
    condition_score,
)
from evaluator.runner import (
    EpisodeCallback,
    OutputCallback,
    RunOptions,
    ShardOutcome,
    failed_episode,
    make_shards,
    run_shard,
)
from evaluator.sources import PolicySource
from evaluator.trajectory import merge_parts, plan_stems


def evaluate(
    plan: EvaluationPlan,
    source: PolicySource,
    *,
    workers: int = 1,
    warm: bool = False,
    video_dir: Path | None = None,
    trajectory_dir: Path | None = None,
    on_episode: EpisodeCallback | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    on_output: OutputCallback | None = None,
) -> EvaluationResult:
    """Run every episode of `plan` against the policy from `source` and score it.

    `should_stop` (a cancel) is polled between steps and every 0.1 s while the policy is
    answering, so a run stops mid-episode, even mid-call; the episode in progress and those not
    started are recorded as `not_run`.

    One worker runs here, in this process, unless `warm`; otherwise the shards run in a warm
    pool of `workers` evaluator processes (`evaluator.pool`), kept for the next evaluation.
    A daemonic process (a Celery prefork child) may start none, and runs one worker here.

    `on_output`, if given, gets the policy processes' own output as it comes, by shard (when
    their launcher can pass it on: local processes and containers).

    With `trajectory_dir`, every episode that ran is kept there in ManiSkill's trajectory
    format, one `<condition>--<Task>.h5` + `.json` per task run (`evaluator.trajectory`).
    """
    started = datetime.now(UTC)
    options = RunOptions(video_dir=video_dir, trajectory_dir=trajectory_dir)
    callback = on_episode or (lambda _run, _episode: None)
    if not can_start_processes():
        workers, warm = 1, False
    shards = make_shards(plan, workers)
    if workers == 1 and not warm:
        outcomes = [
            run_shard(
                plan,
                source,
                shards[0],
                options=options,
                on_episode=callback,
                should_stop=should_stop,
                on_output=None if on_output is None else functools.partial(on_output, 0),
            )
        ]
    else:
        outcomes = run_warm(
            workers, plan, source, shards, options, callback, should_stop, on_output
        )
    if trajectory_dir is not None:
        merge_parts(trajectory_dir, plan_stems(plan))
    provenance = local_provenance(plan, policy_image=source.pinned_image())
    return build_result(plan, source.describe(), outcomes, started=started, provenance=provenance)


def build_result(
    plan: EvaluationPlan,
    policy: str,
    outcomes: list[ShardOutcome],
    *,
    started: datetime,
    finished: Callable[[], datetime] = lambda: datetime.now(UTC),
    versions: Versions | None = None,
    provenance: Provenance | None = None,
) -> EvaluationResult:
    """Merge shard outcomes; planned episodes that never ran are recorded as `not_run`.
    `versions` are those installed here unless given (the shards' own, when merged
    elsewhere); `provenance` is where the episodes ran (`evaluator.provenance`)."""
    by_run: dict[int, dict[int, EpisodeResult]] = {i: {} for i in range(len(plan.runs))}
    for outcome in outcomes:
        for run_index, episode in outcome.episodes:
            by_run[run_index][episode.index] = episode
    aborts = sorted((o.abort for o in outcomes if o.abort), key=lambda a: (a[0], a[1]))
    abort = aborts[0][2] if aborts else None
    conditions: dict[str, ConditionResult] = {}
    for run_index, run in enumerate(plan.runs):
        done = by_run[run_index]
        episodes = [
            done.get(i)
            or failed_episode(
                i,
                seed,
                "not_run",
                "the evaluation stopped before it",
                at_end_measured=plan.ignore_terminations,
            )
            for i, seed in enumerate(run.seeds)
        ]
        condition = conditions.setdefault(
            run.condition.name,
            ConditionResult(
                name=run.condition.name,
                params=run.condition.params.model_dump(),
                score=0.0,
                tasks=[],
            ),
        )
        condition.tasks.append(aggregate_task(run.env_id, len(run.seeds), episodes))
    for condition in conditions.values():
        condition.score = condition_score(condition.tasks)
    ordered = list(conditions.values())
    return EvaluationResult(
        suite=plan.suite,
        phase=plan.phase,
        policy=policy,
        versions=versions or installed_versions(),
        provenance=provenance,
        started_at=started,
        finished_at=finished(),
        status="aborted" if abort else "completed",
        abort=abort,
        budget=BudgetUse(
            budget_s=plan.limits.budget_s, used_s=sum(o.policy_time_s for o in outcomes)
        ),
        score=ordered[0].score if ordered else 0.0,
        conditions=ordered,
        videos=[video for outcome in outcomes for video in outcome.videos],
    )
