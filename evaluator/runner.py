"""Run an evaluation plan against a policy source, optionally sharded over worker processes.

Episodes are split into contiguous chunks per task run, one chunk per worker; each worker owns
its environments and its own policy process. Episode results depend only on (task, condition,
seed, policy), so any number of workers produces the same records.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evaluator.channel import PolicyChannel, RemoteChannel
from evaluator.conditions import ConditionRuntime
from evaluator.endpoint import PolicyEndpoint, PolicyFailure, PolicyRaised, Stopped
from evaluator.episode import run_episode
from evaluator.limits import with_detail
from evaluator.observation import ObservationKeys
from evaluator.packages import import_packages
from evaluator.plan import EvaluationPlan, TaskRun
from evaluator.results import Abort, EpisodeResult, FailureKind, Video
from evaluator.sim import (
    action_bounds,
    control_freq,
    default_control_freq,
    describe_space,
    make_env,
)
from evaluator.sources import EchoingProcess, OutputSink, PolicySource, limit_reached
from evaluator.suite import NO_CHUNKS, ActionChunks
from evaluator.trajectory import TrajectoryRecorder
from evaluator.video import write_video

EpisodeCallback = Callable[[int, EpisodeResult], None]
OutputCallback = Callable[[int, bytes], None]
"""Takes a piece of the output of the policy process of a shard (by its index), as it comes."""
Unit = tuple[int, tuple[tuple[int, int], ...]]  # (run index, ((episode index, seed), ...))


@dataclass(frozen=True)
class Shard:
    """The episodes one worker runs, grouped by task run."""

    units: tuple[Unit, ...]

    def episode_count(self) -> int:
        """Episodes in the shard."""
        return sum(len(episodes) for _, episodes in self.units)


@dataclass
class ShardOutcome:
    """What a worker ran: its episodes, why it stopped early (if it did), its videos, and the
    time its policy took (charged to the budget)."""

    episodes: list[tuple[int, EpisodeResult]] = field(default_factory=list)
    abort: tuple[int, int, Abort] | None = None  # (run index, episode index, why)
    videos: list[Video] = field(default_factory=list)
    policy_time_s: float = 0.0


@dataclass(frozen=True)
class RunOptions:
    """How to run: where videos and trajectories go (none: not recorded), and where the
    endpoint's socket is made (a fresh private directory unless a shared volume is named)."""

    video_dir: Path | None = None
    socket_dir: Path | None = None
    trajectory_dir: Path | None = None


def make_shards(plan: EvaluationPlan, workers: int) -> list[Shard]:
    """Split every task run's episodes into `workers` contiguous chunks."""
    if workers < 1:
        raise ValueError("workers must be at least 1")
    per_worker: list[list[Unit]] = [[] for _ in range(workers)]
    for run_index, run in enumerate(plan.runs):
        pairs = list(enumerate(run.seeds))
        base, extra = divmod(len(pairs), workers)
        start = 0
        for worker in range(workers):
            size = base + (1 if worker < extra else 0)
            if size:
                per_worker[worker].append((run_index, tuple(pairs[start : start + size])))
            start += size
    return [Shard(tuple(units)) for units in per_worker if units]


def task_spec(
    run: TaskRun, env: Any, step_limit: int, chunks: ActionChunks = NO_CHUNKS
) -> dict[str, Any]:
    """The `task` message's spec: what the policy may know about the task."""
    low, high = action_bounds(env)
    return {
        "env_id": run.env_id,
        "obs_mode": run.obs_mode,
        "control_mode": run.control_mode,
        "control_freq": control_freq(env),
        "max_episode_steps": step_limit,
        "action_space": {"low": low, "high": high},
        "observation_space": ObservationKeys(run.observation_keys).space(
            describe_space(env.unwrapped.single_observation_space)
        ),
        "instruction": run.instruction,
        "action_chunks": {"max_length": chunks.max_length, "execute": chunks.executed},
    }


@dataclass
class TaskEnv:
    """A task run's environment, ready for its episodes."""

    env: Any
    runtime: ConditionRuntime
    record: bool
    recorder: TrajectoryRecorder | None = None

    def close(self) -> None:
        """Close the environment, then finish its trajectory file if it is recorded."""
        self.env.close()
        if self.recorder is not None:
            self.recorder.close()


def open_task(
    plan: EvaluationPlan, run_index: int, episodes: Sequence[tuple[int, int]], options: RunOptions
) -> TaskEnv:
    """Build the environment for these episodes of a task run (rendering if one is filmed,
    wrapped in ManiSkill's recorder if trajectories are kept)."""
    run = plan.runs[run_index]
    runtime = ConditionRuntime(run.condition, keys=ObservationKeys(run.observation_keys))
    record = options.video_dir is not None and any(plan.records(run, i) for i, _ in episodes)
    env = make_env(run, runtime, render=record, frame_size=plan.video_size)
    if options.trajectory_dir is None:
        return TaskEnv(env, runtime, record)
    recorder = TrajectoryRecorder(options.trajectory_dir, run=run, first_episode=episodes[0][0])
    return TaskEnv(recorder.wrap(env), runtime, record, recorder)


def run_units(
    plan: EvaluationPlan,
    channel: PolicyChannel,
    units: Sequence[Unit],
    outcome: ShardOutcome,
    *,
    options: RunOptions,
    on_episode: EpisodeCallback,
    should_stop: Callable[[], bool] = lambda: False,
    first: TaskEnv | None = None,
) -> None:
    """Run task runs' episodes through `channel`; PolicyFailure propagates after recording.
    `first`, if given, is the first unit's environment, already built; it is closed here."""
    for position, (run_index, episodes) in enumerate(units):
        task = first if position == 0 else None
        try:
            if should_stop():
                return
            if task is None:
                task = open_task(plan, run_index, episodes, options)
            _run_task(
                plan,
                run_index,
                plan.runs[run_index],
                task,
                channel,
                episodes,
                outcome,
                options=options,
                on_episode=on_episode,
                should_stop=should_stop,
            )
        finally:
            if task is not None:
                task.close()


def _run_task(
    plan: EvaluationPlan,
    run_index: int,
    run: TaskRun,
    task: TaskEnv,
    channel: PolicyChannel,
    episodes: Sequence[tuple[int, int]],
    outcome: ShardOutcome,
    *,
    options: RunOptions,
    on_episode: EpisodeCallback,
    should_stop: Callable[[], bool],
) -> None:
    env, runtime, record = task.env, task.runtime, task.record
    step_limit = runtime.step_limit(run.max_episode_steps, default_control_freq(env))
    bounds = action_bounds(env)
    stride = plan.frame_stride(control_freq(env))
    index, seed = episodes[0]  # where a PolicyFailure is charged
    try:
        setup_error = _start_task(channel, task_spec(run, env, step_limit, plan.action_chunks))
        for index, seed in episodes:
            if should_stop():  # cancelled, or another shard aborted: the rest is not run
                return
            if setup_error is not None:
                result = failed_episode(
                    index,
                    seed,
                    "policy_error",
                    setup_error,
                    at_end_measured=plan.ignore_terminations,
                )
            else:
                frames: list[Any] | None = [] if record and plan.records(run, index) else None
                result = run_episode(
                    env,
                    channel,
                    runtime,
                    index=index,
                    seed=seed,
                    step_limit=step_limit,
                    bounds=bounds,
                    ignore_terminations=plan.ignore_terminations,
                    chunks=plan.action_chunks,
                    frames=frames,
                    frame_every=stride,
                    should_stop=should_stop,
                )
                if task.recorder is not None:
                    task.recorder.episode_done(index)
                if frames and options.video_dir is not None:
                    fps = control_freq(env) / stride
                    outcome.videos.append(
                        write_video(frames, options.video_dir, run=run, episode=index, fps=fps)
                    )
            outcome.episodes.append((run_index, result))
            on_episode(run_index, result)
    except PolicyFailure as failure:
        if failure.episode is not None and task.recorder is not None:
            task.recorder.episode_done(index)  # the steps it took before it broke
        result = failure.episode or failed_episode(
            index, seed, failure.kind, failure.reason, at_end_measured=plan.ignore_terminations
        )
        outcome.episodes.append((run_index, result))
        on_episode(run_index, result)
        outcome.abort = (run_index, index, Abort(kind=failure.kind, reason=failure.reason))
        raise


def _start_task(channel: PolicyChannel, spec: dict[str, Any]) -> str | None:
    """Send the task spec; the policy's own setup error fails the task's episodes, not the run."""
    try:
        channel.start_task(spec)
    except PolicyRaised as exc:
        return f"the policy raised in setup: {exc}"
    return None


def failed_episode(
    index: int, seed: int, kind: FailureKind, reason: str, *, at_end_measured: bool
) -> EpisodeResult:
    """The record of an episode that ended (or never started) because of the policy."""
    return EpisodeResult(
        index=index,
        seed=seed,
        success_once=False,
        success_at_end=False if at_end_measured else None,
        steps=0,
        episode_return=0.0,
        wall_time_s=0.0,
        failure=kind,
        failure_reason=reason,
    )


def run_shard(
    plan: EvaluationPlan,
    source: PolicySource,
    shard: Shard,
    *,
    options: RunOptions,
    on_episode: EpisodeCallback,
    should_stop: Callable[[], bool] = lambda: False,
    on_output: OutputSink | None = None,
) -> ShardOutcome:
    """Start a policy process, run the shard's episodes through it, always stop it. The
    policy's output goes to `on_output` as it comes, when given and its launcher can."""
    import_packages(plan.packages)  # before the policy starts: a wrong version runs nothing
    outcome = ShardOutcome()
    limits = plan.limits
    endpoint = PolicyEndpoint(
        socket_dir=options.socket_dir,
        max_frame_bytes=limits.max_action_frame_bytes,
        budget_s=budget_share(plan, shard),
    )
    endpoint.should_stop = should_stop
    process = source.launch(endpoint=endpoint.address, socket_dir=endpoint.socket_dir)
    if on_output is not None and isinstance(process, EchoingProcess):
        process.echo(on_output)
    first: TaskEnv | None = None
    try:
        # Built while the policy process starts: the two start-ups overlap.
        first = open_task(plan, *shard.units[0], options)
        endpoint.accept(timeout=limits.connect_timeout_s, alive=process.alive)
        endpoint.hello(timeout=limits.first_call_timeout_s)
        channel = RemoteChannel(endpoint, limits)
        handed, first = first, None  # run_units closes it from here on
        run_units(
            plan,
            channel,
            shard.units,
            outcome,
            options=options,
            on_episode=on_episode,
            should_stop=should_stop,
            first=handed,
        )
    except PolicyFailure as failure:
        if outcome.abort is None:  # it broke before its first episode: none of them ran
            first_run, episodes = shard.units[0]
            index, _ = episodes[0]
            outcome.abort = (first_run, index, Abort(kind=failure.kind, reason=failure.reason))
    except Stopped:
        pass  # cancelled: the episode in progress, and those after it, are recorded not_run
    finally:
        try:  # whatever fails on the way out, the policy is stopped (its container removed)
            if first is not None:
                first.close()
            outcome.policy_time_s = endpoint.policy_time_s
            code = process.exit_code()  # before stop(): our own SIGTERM is not the policy's exit
            endpoint.close()
        finally:
            process.stop()
    if outcome.abort is not None:
        run_index, index, abort = outcome.abort
        kind = limit_reached(process) or abort.kind  # a sandbox stopped it at a resource limit
        ended = process.exit_detail() or (None if code in (None, 0) else f"exit code {code}")
        reason = abort.reason if ended is None else with_detail(abort.reason, ended)
        tail = process.log_tail()
        outcome.abort = (
            run_index,
            index,
            abort.model_copy(update={"kind": kind, "reason": reason, "log_tail": tail}),
        )
        if kind != abort.kind:  # the episode it broke in is charged with the limit, too
            outcome.episodes = [
                (r, e.model_copy(update={"failure": kind, "failure_reason": reason}))
                if (r, e.index) == (run_index, index)
                else (r, e)
                for r, e in outcome.episodes
            ]
    return outcome


def budget_share(plan: EvaluationPlan, shard: Shard) -> float:
    """The part of the plan's time budget a shard's policy process gets: its share of the
    episodes, so that the whole evaluation gets the budget however it is sharded."""
    return plan.limits.budget_s * shard.episode_count() / max(plan.episode_count(), 1)
