"""Evaluate a plan: shard it over worker processes, merge their episodes into one result."""

from __future__ import annotations

import multiprocessing
import platform
import queue
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

from evaluator.plan import EvaluationPlan
from evaluator.results import (
    BudgetUse,
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    Versions,
    aggregate_task,
    condition_score,
)
from evaluator.runner import (
    EpisodeCallback,
    RunOptions,
    Shard,
    ShardOutcome,
    failed_episode,
    make_shards,
    run_shard,
)
from evaluator.sources import PolicySource

_worker_events: Any = None
_worker_stop: Any = None


def evaluate(
    plan: EvaluationPlan,
    source: PolicySource,
    *,
    workers: int = 1,
    video_dir: Path | None = None,
    on_episode: EpisodeCallback | None = None,
    should_stop: Callable[[], bool] = lambda: False,
) -> EvaluationResult:
    """Run every episode of `plan` against the policy from `source` and score it.

    `should_stop` (a cancel) is polled between steps and every 0.1 s while the policy is
    answering, so a run stops mid-episode, even mid-call; the episode in progress and those not
    started are recorded as `not_run`.
    """
    started = datetime.now(UTC)
    options = RunOptions(video_dir=video_dir)
    callback = on_episode or (lambda _run, _episode: None)
    shards = make_shards(plan, workers)
    if len(shards) == 1:
        outcomes = [
            run_shard(
                plan,
                source,
                shards[0],
                options=options,
                on_episode=callback,
                should_stop=should_stop,
            )
        ]
    else:
        outcomes = _run_parallel(plan, source, shards, options, callback, should_stop)
    return build_result(plan, source.describe(), outcomes, started=started)


def _run_parallel(
    plan: EvaluationPlan,
    source: PolicySource,
    shards: list[Shard],
    options: RunOptions,
    callback: EpisodeCallback,
    should_stop: Callable[[], bool],
) -> list[ShardOutcome]:
    # spawn, not fork: torch and SAPIEN hold threads and GPU/Vulkan state that fork would copy.
    context = multiprocessing.get_context("spawn")
    events = context.Queue()
    stop = context.Event()
    pool = ProcessPoolExecutor(
        max_workers=len(shards),
        mp_context=context,
        initializer=_init_worker,
        initargs=(events, stop),
    )
    try:
        futures = [pool.submit(_shard_in_worker, plan, source, shard, options) for shard in shards]
        _pump_events(futures, events, callback, stop, should_stop)
        return [future.result() for future in futures]
    finally:
        # Normally every shard has returned by now, its policy stopped: the worker processes'
        # own exit (unloading torch and SAPIEN) need not delay the result, nor a cancel. If we
        # got here by an exception, the stop makes the shards still running end soon.
        stop.set()
        pool.shutdown(wait=False, cancel_futures=True)


def _pump_events(
    futures: list[Future[ShardOutcome]],
    events: Any,
    callback: EpisodeCallback,
    stop: Any,
    should_stop: Callable[[], bool],
) -> None:
    while True:
        if should_stop():
            stop.set()
        done = all(f.done() for f in futures)
        try:
            kind, run_index, payload = events.get(timeout=0.1)
        except queue.Empty:
            if done:
                return
            continue
        if kind == "episode":
            callback(run_index, EpisodeResult.model_validate(payload))
        elif kind == "abort":
            stop.set()


def _init_worker(events: Any, stop: Any) -> None:
    global _worker_events, _worker_stop
    _worker_events, _worker_stop = events, stop


def _shard_in_worker(
    plan: EvaluationPlan, source: PolicySource, shard: Shard, options: RunOptions
) -> ShardOutcome:
    def report(run_index: int, episode: EpisodeResult) -> None:
        _worker_events.put(("episode", run_index, episode.model_dump(mode="json")))

    outcome = run_shard(
        plan, source, shard, options=options, on_episode=report, should_stop=_worker_stop.is_set
    )
    if outcome.abort is not None:
        _worker_events.put(("abort", outcome.abort[0], None))
    return outcome


def build_result(
    plan: EvaluationPlan,
    policy: str,
    outcomes: list[ShardOutcome],
    *,
    started: datetime,
    finished: Callable[[], datetime] = lambda: datetime.now(UTC),
) -> EvaluationResult:
    """Merge shard outcomes; planned episodes that never ran are recorded as `not_run`."""
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
        versions=installed_versions(),
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


def installed_versions() -> Versions:
    """Versions of everything that decides the numbers, for the result document."""
    return Versions(
        manieval=metadata.version("manieval"),
        mani_skill=metadata.version("mani_skill"),
        sapien=metadata.version("sapien"),
        torch=metadata.version("torch"),
        python=platform.python_version(),
    )
