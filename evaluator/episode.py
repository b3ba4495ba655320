"""One episode: reset with a seed, then act and step until the task ends or the limit is hit."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from evaluator.channel import PolicyChannel
from evaluator.conditions import ConditionRuntime
from evaluator.endpoint import PolicyFailure, PolicyRaised, Stopped
from evaluator.results import EpisodeResult, FailureKind
from evaluator.sim import flag, reward_value, to_numpy


def action_problem(action: Any, shape: tuple[int, ...]) -> str | None:
    """Why an action cannot be applied, or None when it can (after clipping)."""
    if not isinstance(action, np.ndarray):
        return f"action must be a number array, got {type(action).__name__}"
    if action.dtype.kind not in "fiu":
        return f"action has dtype {action.dtype}, a number array is needed"
    if action.shape != shape:
        return f"action has shape {action.shape}, the task needs {shape}"
    if not np.all(np.isfinite(action)):
        return "action contains NaN or infinity"
    return None


@dataclass
class Progress:
    """How far an episode got."""

    steps: int = 0
    episode_return: float = 0.0
    clipped: int = 0
    success_once: bool = False
    success_at_end: bool = False
    filmed: int = -1  # the last step whose frame was recorded (0: the reset state)


def run_episode(
    env: Any,
    channel: PolicyChannel,
    runtime: ConditionRuntime,
    *,
    index: int,
    seed: int,
    step_limit: int,
    bounds: tuple[np.ndarray, np.ndarray],
    ignore_terminations: bool,
    frames: list[np.ndarray] | None = None,
    frame_every: int = 1,
    should_stop: Callable[[], bool] = lambda: False,
) -> EpisodeResult:
    """Run one episode; policy-level failures end it as a failure with a reason.

    With `ignore_terminations` the episode runs to `step_limit` whatever the task signals, and
    success at the last step is measured; otherwise it ends at the first termination (success)
    and `success_at_end` is null. A PolicyFailure (an abort) propagates, carrying the episode's
    record so far; so does Stopped, when `should_stop` (polled between steps) says so.

    With `frames`, the episode is filmed into it: the reset state, then the state after every
    `frame_every`-th step, and after the last step whatever its number.
    """
    if frame_every < 1:
        raise ValueError(f"frame_every must be at least 1, not {frame_every}")
    started = time.perf_counter()
    policy_time_before = channel.policy_time_s
    raw_obs, _ = env.reset(seed=seed)
    seen = runtime.begin_episode(seed, to_numpy(raw_obs))
    progress = Progress()
    _film(env, frames, progress, every=1)  # the reset state: before the policy's first action

    def record(failure: tuple[FailureKind, str] | None) -> EpisodeResult:
        failed = failure is not None
        return EpisodeResult(
            index=index,
            seed=seed,
            success_once=progress.success_once and not failed,
            success_at_end=(progress.success_at_end and not failed)
            if ignore_terminations
            else None,
            steps=progress.steps,
            episode_return=progress.episode_return,
            wall_time_s=time.perf_counter() - started,
            policy_time_s=channel.policy_time_s - policy_time_before,
            invalid_actions=int(failure is not None and failure[0] == "invalid_action"),
            clipped_actions=progress.clipped,
            failure=failure[0] if failure else None,
            failure_reason=failure[1] if failure else None,
        )

    try:
        channel.reset(seen, {"episode": index})
        problem = _play(
            env,
            channel,
            runtime,
            seen,
            progress,
            step_limit,
            bounds,
            ignore_terminations,
            frames,
            frame_every,
            should_stop,
        )
        _film(env, frames, progress, every=1)
        return record(("invalid_action", problem) if problem else None)
    except PolicyRaised as exc:
        _film(env, frames, progress, every=1)
        return record(("policy_error", f"the policy raised: {exc}"))
    except PolicyFailure as failure:
        failure.episode = record((failure.kind, failure.reason))
        raise


def _play(
    env: Any,
    channel: PolicyChannel,
    runtime: ConditionRuntime,
    seen: Any,
    progress: Progress,
    step_limit: int,
    bounds: tuple[np.ndarray, np.ndarray],
    ignore_terminations: bool,
    frames: list[np.ndarray] | None,
    frame_every: int,
    should_stop: Callable[[], bool],
) -> str | None:
    """Act and step until the episode ends; why an action could not be applied, if one was not."""
    low, high = bounds
    record = _StepRecord(progress)  # the last step's: none yet
    try:
        while progress.steps < step_limit:
            if should_stop():
                raise Stopped()
            action = channel.act(seen, meanwhile=record)  # recorded while the policy thinks
            record()  # a no-op if the channel did it
            problem = action_problem(action, low.shape)
            if problem:
                return problem
            wide = action.astype(np.float64)
            applied = np.clip(wide, low, high)
            progress.clipped += int(not np.array_equal(applied, wide))
            raw_obs, reward, terminated, truncated, info = env.step(applied.astype(np.float32))
            progress.steps += 1
            record = _StepRecord(progress, reward, info["success"])
            _film(env, frames, progress, every=frame_every)
            if not ignore_terminations and (flag(terminated) or flag(truncated)):
                return None
            seen = runtime.observe(to_numpy(raw_obs))
        return None
    finally:
        record()  # the last step's, unless the policy's last call already took care of it


class _StepRecord:
    """Adds a step's reward and success to the episode's progress, once however often it is
    called.

    The policy needs neither, so the episode loop records them while the policy thinks about
    the next action (a remote policy thinks in its own process meanwhile), or when the episode
    ends. The sums are the same, in the same order, either way.
    """

    def __init__(self, progress: Progress, reward: Any = None, success: Any = None) -> None:
        self._progress = progress
        self._step: tuple[Any, Any] | None = None if reward is None else (reward, success)

    def __call__(self) -> None:
        if self._step is not None:
            (reward, success), self._step = self._step, None
            progress = self._progress
            progress.episode_return += reward_value(reward)
            progress.success_at_end = flag(success)
            progress.success_once = progress.success_once or progress.success_at_end


def _film(env: Any, frames: list[np.ndarray] | None, progress: Progress, *, every: int) -> None:
    """Record the current state's frame if the episode is filmed, its step is on the film's
    cadence (`every`), and it was not recorded yet."""
    if frames is not None and progress.filmed != progress.steps and progress.steps % every == 0:
        frames.append(to_numpy(env.render()))
        progress.filmed = progress.steps
