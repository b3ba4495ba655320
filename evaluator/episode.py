"""One episode: reset with a seed, then act and step until the task ends or the limit is hit.

The policy answers each `act` with one action or a chunk of them; either way every control step
is applied, checked and recorded alike (docs/protocol.md, "Action chunks")."""

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
from evaluator.suite import NO_CHUNKS, ActionChunks


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


def chunk_problem(actions: Any, shape: tuple[int, ...], max_length: int) -> str | None:
    """Why a chunk of actions cannot be applied, or None when it can: the checks of one action,
    for each of them, and a length from 1 to `max_length`."""
    if not isinstance(actions, np.ndarray):
        return f"actions must be a number array, got {type(actions).__name__}"
    if actions.dtype.kind not in "fiu":
        return f"actions has dtype {actions.dtype}, a number array is needed"
    if actions.ndim != len(shape) + 1 or actions.shape[1:] != shape:
        needed = ", ".join(["H", *map(str, shape)])
        return f"actions has shape {actions.shape}, a chunk for the task is ({needed})"
    if not 1 <= len(actions) <= max_length:
        return f"a chunk of {len(actions)} actions, the suite takes 1 to {max_length}"
    if not np.all(np.isfinite(actions)):
        return "actions contains NaN or infinity"
    return None


def chunk_of(answer: dict[str, Any], shape: tuple[int, ...], max_length: int) -> np.ndarray | str:
    """The actions an answer to `act` asks for, as a chunk (one action: a chunk of one), or why
    they cannot be applied; nothing of a chunk is applied unless all of it can be."""
    if "actions" not in answer:
        action = answer.get("action")
        problem = action_problem(action, shape)
        return problem or np.asarray(action)[np.newaxis]
    if "action" in answer:
        return "an answer carries either 'action' or 'actions', not both"
    return chunk_problem(answer["actions"], shape, max_length) or answer["actions"]


@dataclass
class Progress:
    """How far an episode got."""

    steps: int = 0
    episode_return: float = 0.0
    clipped: int = 0
    success_once: bool = False
    success_at_end: bool = False
    filmed: int = -1  # the last step whose frame was recorded (0: the reset state)


@dataclass(frozen=True)
class Rules:
    """What an episode keeps to: its step limit, the action bounds, the chunks it takes, when
    it ends, what is filmed, and when to stop early."""

    step_limit: int
    bounds: tuple[np.ndarray, np.ndarray]
    ignore_terminations: bool
    chunks: ActionChunks
    frames: list[np.ndarray] | None
    frame_every: int
    should_stop: Callable[[], bool]


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
    chunks: ActionChunks = NO_CHUNKS,
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
    rules = Rules(step_limit, bounds, ignore_terminations, chunks, frames, frame_every, should_stop)
    started = time.perf_counter()
    policy_time_before = channel.policy_time_s
    raw_obs, _ = env.reset(seed=seed)
    seen = runtime.begin_episode(seed, to_numpy(raw_obs))
    progress = Progress()
    _film(env, rules, progress, every=1)  # the reset state: before the policy's first action

    def record(failure: tuple[FailureKind, str] | None) -> EpisodeResult:
        time_s = time.perf_counter() - started
        policy_time_s = channel.policy_time_s - policy_time_before
        return _result(index, seed, progress, rules, failure, time_s, policy_time_s)

    try:
        channel.reset(seen, {"episode": index})
        problem = _Player(env, channel, runtime, progress, rules).play(seen)
        _film(env, rules, progress, every=1)
        return record(("invalid_action", problem) if problem else None)
    except PolicyRaised as exc:
        _film(env, rules, progress, every=1)
        return record(("policy_error", f"the policy raised: {exc}"))
    except PolicyFailure as failure:
        failure.episode = record((failure.kind, failure.reason))
        raise


def _result(
    index: int,
    seed: int,
    progress: Progress,
    rules: Rules,
    failure: tuple[FailureKind, str] | None,
    wall_time_s: float,
    policy_time_s: float,
) -> EpisodeResult:
    """The episode's record: a failure takes its successes away."""
    failed = failure is not None
    at_end = progress.success_at_end and not failed
    return EpisodeResult(
        index=index,
        seed=seed,
        success_once=progress.success_once and not failed,
        success_at_end=at_end if rules.ignore_terminations else None,
        steps=progress.steps,
        episode_return=progress.episode_return,
        wall_time_s=wall_time_s,
        policy_time_s=policy_time_s,
        invalid_actions=int(failure is not None and failure[0] == "invalid_action"),
        clipped_actions=progress.clipped,
        failure=failure[0] if failure else None,
        failure_reason=failure[1] if failure else None,
    )


class _Player:
    """Asks the policy and steps the simulator until the episode ends.

    Each answer is a chunk of actions (one action is a chunk of one); up to the suite's
    `execute` of them are applied, one control step each, before the policy is asked again
    with the latest observation. Every step is recorded as if it had been asked for alone.
    """

    def __init__(
        self,
        env: Any,
        channel: PolicyChannel,
        runtime: ConditionRuntime,
        progress: Progress,
        rules: Rules,
    ) -> None:
        self._env, self._channel, self._runtime = env, channel, runtime
        self._progress, self._rules = progress, rules
        self._pending = _StepRecord(progress)  # the last step's record: none yet

    def play(self, seen: Any) -> str | None:
        """Play from what the policy sees first; why an answer could not be applied, if one
        was not."""
        rules = self._rules
        shape = rules.bounds[0].shape
        try:
            while self._progress.steps < rules.step_limit:
                self._check_stop()
                # The last step is recorded while the policy thinks about the next.
                answer = self._channel.act(seen, meanwhile=self._pending)
                self._pending()  # a no-op if the channel did it
                chunk = chunk_of(answer, shape, rules.chunks.max_length)
                if isinstance(chunk, str):
                    return chunk
                seen = self._execute(chunk[: rules.chunks.executed])
                if seen is None:
                    return None
            return None
        finally:
            self._pending()  # the last step's, unless the policy's last call took care of it

    def _execute(self, actions: np.ndarray) -> Any:
        """Apply a chunk's actions in turn; what the policy sees next, None if the episode
        ended first (the actions left are dropped)."""
        runtime, last = self._runtime, len(actions) - 1
        seen = None
        for n, action in enumerate(actions):
            if n:  # within a chunk nobody thinks meanwhile: record the step before at once
                self._check_stop()
                self._pending()
            raw_obs, ended = self._step(action)
            if ended:
                return None
            # The policy sees only the chunk's last observation; a condition with a memory
            # (a delay, a noise stream) still takes every step's.
            if n == last or runtime.observes_every_step:
                seen = runtime.observe(to_numpy(raw_obs))
        return seen

    def _step(self, action: np.ndarray) -> tuple[Any, bool]:
        """One control step with a valid action, clipped to the bounds: the observation after
        it, and whether the episode is over."""
        progress, rules = self._progress, self._rules
        low, high = rules.bounds
        wide = action.astype(np.float64)
        applied = np.clip(wide, low, high)
        progress.clipped += int(not np.array_equal(applied, wide))
        raw_obs, reward, terminated, truncated, info = self._env.step(applied.astype(np.float32))
        progress.steps += 1
        self._pending = _StepRecord(progress, reward, info["success"])
        _film(self._env, rules, progress, every=rules.frame_every)
        ended = not rules.ignore_terminations and (flag(terminated) or flag(truncated))
        return raw_obs, ended or progress.steps >= rules.step_limit

    def _check_stop(self) -> None:
        if self._rules.should_stop():
            raise Stopped()


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


def _film(env: Any, rules: Rules, progress: Progress, *, every: int) -> None:
    """Record the current state's frame if the episode is filmed, its step is on the film's
    cadence (`every`), and it was not recorded yet."""
    frames = rules.frames
    if frames is not None and progress.filmed != progress.steps and progress.steps % every == 0:
        frames.append(to_numpy(env.render()))
        progress.filmed = progress.steps
