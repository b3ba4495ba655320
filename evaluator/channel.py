"""How the episode loop talks to a policy: over the wire protocol, or in-process for baselines.

The in-process channel exists so that tests and `bench/` can compare the protocol against a
plain function call with everything else held equal; submissions always use `RemoteChannel`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

from evaluator.endpoint import PolicyEndpoint, PolicyRaised
from evaluator.suite import Limits
from manieval_sdk import Policy, TaskSpec
from manieval_sdk.serve import action_reply, task_spec
from manieval_sdk.wire import PROTOCOL_VERSION


class PolicyChannel(Protocol):
    """The three calls the evaluator makes of a policy during a task."""

    @property
    def policy_time_s(self) -> float:
        """Time the policy has taken so far answering `reset` and `act` (its budget's clock)."""
        ...

    def start_task(self, spec: dict[str, Any]) -> None: ...

    def reset(self, obs: Any, info: dict[str, Any]) -> None: ...

    def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
        """The policy's answer for `obs`: `action`, one action, or `actions`, a chunk of them
        (unchecked); `meanwhile` is the evaluator's own work, done while the policy thinks
        where it thinks elsewhere, and never charged to the policy."""
        ...


class RemoteChannel:
    """A policy in another process, behind a connected `PolicyEndpoint`."""

    def __init__(self, endpoint: PolicyEndpoint, limits: Limits) -> None:
        self._endpoint = endpoint
        self._limits = limits
        self._warm = False

    @property
    def policy_time_s(self) -> float:
        """Time the policy has taken so far answering `reset` and `act`."""
        return self._endpoint.policy_time_s

    def start_task(self, spec: dict[str, Any]) -> None:
        """Send the task spec (set-up, not charged to the budget); the first act after it gets
        the generous timeout."""
        self._endpoint.call(
            {"type": "task", "spec": spec},
            expect="ok",
            timeout=self._limits.first_call_timeout_s,
            charged=False,
        )
        self._warm = False

    def reset(self, obs: Any, info: dict[str, Any]) -> None:
        """Start an episode."""
        self._endpoint.call(
            {"type": "reset", "obs": obs, "info": info},
            expect="ok",
            timeout=self._limits.call_timeout_s,
        )

    def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
        """One answer; warm-up (JIT, lazy loading) is allowed the first-call timeout.
        `meanwhile` runs once the observation is sent, while the policy's process thinks."""
        timeout = self._limits.call_timeout_s if self._warm else self._limits.first_call_timeout_s
        answer = self._endpoint.act(obs, timeout=timeout, meanwhile=meanwhile)
        self._warm = True
        return answer


class InProcessChannel:
    """A `Policy` object called directly: for baselines and benchmarks, never for submissions."""

    def __init__(self, policy: Policy) -> None:
        self._policy = policy
        self._spec: TaskSpec | None = None
        self.policy_time_s = 0.0

    def start_task(self, spec: dict[str, Any]) -> None:
        """Set the policy up for a task."""
        parsed = self._spec = task_spec(spec)
        self._guard(lambda: self._policy.setup(parsed))

    def reset(self, obs: Any, info: dict[str, Any]) -> None:
        """Start an episode."""
        self._timed(lambda: self._policy.reset(obs, info))

    def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
        """One answer, as the SDK would send it over the wire (protocol 2); `meanwhile` first,
        as the policy runs in this thread."""
        meanwhile()
        reply = self._timed(
            lambda: action_reply(self._policy.act(obs), self._spec, protocol=PROTOCOL_VERSION)
        )
        return {name: value for name, value in reply.items() if name != "type"}

    def _timed(self, call: Any) -> Any:
        started = time.monotonic()
        try:
            return self._guard(call)
        finally:
            self.policy_time_s += time.monotonic() - started

    @staticmethod
    def _guard(call: Any) -> Any:
        try:
            return call()
        except Exception as exc:
            raise PolicyRaised(f"{type(exc).__name__}: {exc}") from exc
