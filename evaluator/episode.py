"""One episode: reset with a seed, then act and step until the task ends or the limit is hit."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from evaluator.channel import PolicyChannel
from evaluator.conditions import ConditionRuntime
from evaluator.endpoint import PolicyRaised
from evaluator.results import EpisodeResult
from evaluator.sim import flag, to_numpy


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
) -> EpisodeResult:
    """Run one episode; policy-level failures end it as a failure with a reason.

    With `ignore_terminations` the episode runs to `step_limit` whatever the task signals, and
    success at the last step is measured; otherwise it ends at the first termination (success)
    and `success_at_end` is null.
    """
    started = time.perf_counter()
    low, high = bounds
    raw_obs, _ = env.reset(seed=seed)
    seen = runtime.begin_episode(seed, to_numpy(raw_obs))
    steps, total, clipped = 0, 0.0, 0
    success_once = success_at_end = False
    failure: tuple[Any, str] | None = None
    try:
        channel.reset(seen, {"episode": index})
        while steps < step_limit:
            action = channel.act(seen)
            problem = action_problem(action, low.shape)
            if problem:
                failure = ("invalid_action", problem)
                break
            wide = action.astype(np.float64)
            applied = np.clip(wide, low, high)
            clipped += int(not np.array_equal(applied, wide))
            raw_obs, reward, terminated, truncated, info = env.step(applied.astype(np.float32))
            steps += 1
            total += float(to_numpy(reward))
            success_at_end = flag(info["success"])
            success_once = success_once or success_at_end
            if frames is not None:
                frames.append(to_numpy(env.render()))
            if not ignore_terminations and (flag(terminated) or flag(truncated)):
                break
            seen = runtime.observe(to_numpy(raw_obs))
    except PolicyRaised as exc:
        failure = ("policy_error", f"the policy raised: {exc}")
    return EpisodeResult(
        index=index,
        seed=seed,
        success_once=success_once and failure is None,
        success_at_end=(success_at_end and failure is None) if ignore_terminations else None,
        steps=steps,
        episode_return=total,
        wall_time_s=time.perf_counter() - started,
        invalid_actions=int(failure is not None and failure[0] == "invalid_action"),
        clipped_actions=clipped,
        failure=failure[0] if failure else None,
        failure_reason=failure[1] if failure else None,
    )
