"""Policies that misbehave: each ends with a clear recorded reason; none hangs the evaluator."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from evaluator.results import EvaluationResult
from tests.evaluator.conftest import run, tiny_plan, with_limits

pytestmark = pytest.mark.sim

HEADER = """
import os, socket, struct, sys, time
import numpy as np
from manieval_sdk import Policy, serve
from manieval_sdk.serve import connect
from manieval_sdk.wire import encode_frame, recv_message
"""


def evaluate_policy(
    make_policy: Callable[[str], Path], body: str, **limits: float
) -> EvaluationResult:
    plan = with_limits(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=2), **limits
    )
    # Given up on, not hung: a hang fails by the suite's timeout (pytest-timeout), and each test
    # asserts which limit ended the episodes. No wall-clock bound: a busy machine is slow.
    return run(plan, make_policy(HEADER + body))


def episodes(result: EvaluationResult) -> list[tuple[str | None, str | None]]:
    return [(e.failure, e.failure_reason) for e in result.conditions[0].tasks[0].episodes]


def assert_aborted(
    result: EvaluationResult, kind: str, reason: str, *, started: bool = True
) -> None:
    """Aborted for `kind`; the episode it broke in is charged with it, unless it broke before
    its first episode (`started=False`): then no episode ran."""
    assert result.status == "aborted"
    assert result.abort is not None
    assert result.abort.kind == kind
    assert reason in result.abort.reason
    assert result.score == 0.0
    failures = [f for f, _ in episodes(result)]
    if not started:
        assert set(failures) == {"not_run"}, failures
    else:
        assert failures[0] == kind
        assert set(failures[1:]) <= {"not_run"}


def test_policy_that_crashes_mid_episode_aborts_with_its_stderr(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Crash(Policy):
    def act(self, obs):
        print("about to fail: out of cheese", file=sys.stderr, flush=True)
        os._exit(3)
serve(Crash())
""",
    )
    assert_aborted(result, "policy_crashed", "closed the connection")
    assert "exit code 3" in result.abort.reason
    assert "out of cheese" in result.abort.log_tail


def test_policy_that_dies_before_connecting_aborts_quickly_with_its_traceback(make_policy):
    result = evaluate_policy(make_policy, "raise ImportError('no module named torch_magic')\n")
    assert_aborted(result, "policy_crashed", "exited before connecting", started=False)
    assert "torch_magic" in result.abort.log_tail


def test_policy_that_hangs_times_out(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Hang(Policy):
    def act(self, obs):
        time.sleep(3600)
serve(Hang())
""",
        first_call_timeout_s=1.5,
    )
    assert_aborted(result, "policy_timeout", "no answer to 'act' within 1.5s")


def test_policy_that_never_connects_times_out(make_policy):
    result = evaluate_policy(make_policy, "time.sleep(3600)\n", connect_timeout_s=1.0)
    assert_aborted(result, "policy_timeout", "did not connect within 1s", started=False)


def test_policy_that_drips_bytes_cannot_extend_its_deadline(make_policy):
    result = evaluate_policy(
        make_policy,
        """
sock = connect(os.environ["MANIEVAL_ENDPOINT"])
recv_message(sock)
frame = encode_frame({"type": "ready", "protocol": 1})
for byte in frame:
    sock.sendall(bytes([byte]))
    time.sleep(0.5)
time.sleep(3600)
""",
        first_call_timeout_s=1.0,
    )
    assert_aborted(result, "policy_timeout", "no answer to 'hello'", started=False)


def test_nan_action_fails_the_episode_and_the_evaluation_goes_on(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class NaN(Policy):
    def act(self, obs):
        return np.full(self.spec.action_shape, np.nan, dtype=np.float32)
serve(NaN())
""",
    )
    assert result.status == "completed"
    assert episodes(result) == [("invalid_action", "action contains NaN or infinity")] * 2
    assert [e.invalid_actions for e in result.conditions[0].tasks[0].episodes] == [1, 1]


def test_wrong_shape_action_fails_the_episode_with_the_shapes_named(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Short(Policy):
    def act(self, obs):
        return np.zeros(3, dtype=np.float32)
serve(Short())
""",
    )
    assert result.status == "completed"
    assert (
        episodes(result) == [("invalid_action", "action has shape (3,), the task needs (7,)")] * 2
    )


def test_out_of_bounds_actions_are_clipped_and_counted(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Wild(Policy):
    def act(self, obs):
        return np.full(self.spec.action_shape, 50.0)
serve(Wild())
""",
    )
    assert result.status == "completed"
    task = result.conditions[0].tasks[0]
    assert [e.failure for e in task.episodes] == [None, None]
    assert all(e.clipped_actions == e.steps > 0 for e in task.episodes)


def test_policy_exception_fails_the_episode_with_the_message(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Buggy(Policy):
    def act(self, obs):
        raise KeyError("gripper_cam")
serve(Buggy())
""",
    )
    assert result.status == "completed"
    assert episodes(result) == [("policy_error", "the policy raised: KeyError: 'gripper_cam'")] * 2


def test_oversized_frame_aborts_as_a_protocol_error(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Huge(Policy):
    def act(self, obs):
        return np.zeros(4_000_000, dtype=np.float32)
serve(Huge())
""",
    )
    assert_aborted(result, "protocol_error", "exceeds the 1048576 limit")


def test_garbage_bytes_abort_as_a_protocol_error(make_policy):
    result = evaluate_policy(
        make_policy,
        """
sock = connect(os.environ["MANIEVAL_ENDPOINT"])
recv_message(sock)
sock.sendall(struct.pack(">I", 16) + b"\\xc1" * 16)
time.sleep(3600)
""",
    )
    assert_aborted(result, "protocol_error", "malformed message", started=False)


def test_unexpected_reply_type_aborts_as_a_protocol_error(make_policy):
    result = evaluate_policy(
        make_policy,
        """
sock = connect(os.environ["MANIEVAL_ENDPOINT"])
recv_message(sock)
sock.sendall(encode_frame({"type": "score", "value": 1.0}))
time.sleep(3600)
""",
    )
    assert_aborted(
        result, "protocol_error", "expected 'ready' after 'hello', got 'score'", started=False
    )


def test_socket_closed_mid_episode_aborts_even_if_the_process_lives_on(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Quitter(Policy):
    calls = 0
    def act(self, obs):
        Quitter.calls += 1
        if Quitter.calls == 5:
            for fd in range(3, 64):
                try:
                    s = socket.socket(fileno=os.dup(fd)); s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        return np.zeros(self.spec.action_shape, dtype=np.float32)
serve(Quitter())
""",
    )
    assert_aborted(result, "policy_crashed", "closed the connection during 'act'")
    first = result.conditions[0].tasks[0].episodes[0]
    assert first.failure == "policy_crashed"


def test_stdout_spam_is_drained_and_capped_while_scoring_goes_on(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Spam(Policy):
    def act(self, obs):
        sys.stdout.write("x" * 1_000_000 + "\\n")
        return np.zeros(self.spec.action_shape, dtype=np.float32)
serve(Spam())
""",
    )
    assert result.status == "completed"
    assert [e.failure for e in result.conditions[0].tasks[0].episodes] == [None, None]


def test_budget_exhaustion_aborts_the_evaluation(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class Slow(Policy):
    def act(self, obs):
        time.sleep(0.5)
        return np.zeros(self.spec.action_shape, dtype=np.float32)
serve(Slow())
""",
        budget_s=3.0,
    )
    assert_aborted(result, "budget_exhausted", "time budget ran out")


def test_setup_error_fails_that_tasks_episodes(make_policy):
    result = evaluate_policy(
        make_policy,
        """
class NoSetup(Policy):
    def setup(self, spec):
        raise RuntimeError("weights missing")
    def act(self, obs):
        return np.zeros(7, dtype=np.float32)
serve(NoSetup())
""",
    )
    assert result.status == "completed"
    reasons = {r for _, r in episodes(result)}
    assert reasons == {"the policy raised in setup: RuntimeError: weights missing"}


def test_error_reply_to_the_handshake_aborts_as_a_protocol_error(make_policy):
    result = evaluate_policy(
        make_policy,
        """
sock = connect(os.environ["MANIEVAL_ENDPOINT"])
recv_message(sock)
sock.sendall(encode_frame({"type": "error", "message": "I do not speak v1"}))
time.sleep(3600)
""",
    )
    assert_aborted(
        result, "protocol_error", "refused the handshake: I do not speak v1", started=False
    )


def test_list_action_fails_the_episode_as_invalid(make_policy):
    result = evaluate_policy(
        make_policy,
        """
sock = connect(os.environ["MANIEVAL_ENDPOINT"])
while True:
    kind = recv_message(sock)["type"]
    reply = {"hello": {"type": "ready", "protocol": 1},
             "act": {"type": "action", "action": [0.0] * 7}}
    sock.sendall(encode_frame(reply.get(kind, {"type": "ok"})))
""",
    )
    assert result.status == "completed"
    assert episodes(result) == [("invalid_action", "action must be a number array, got list")] * 2


def test_failure_when_a_later_task_starts_is_charged_to_that_task(make_policy):
    plan = with_limits(tiny_plan(conditions=["nominal"], episodes=2), first_call_timeout_s=1.5)
    result = run(
        plan,
        make_policy(
            HEADER
            + """
class SecondTaskHangs(Policy):
    def setup(self, spec):
        if spec.env_id == "PushCube-v1":
            time.sleep(3600)
    def act(self, obs):
        return np.zeros(7, dtype=np.float32)
serve(SecondTaskHangs())
"""
        ),
    )
    pick, push = result.conditions[0].tasks
    assert [e.failure for e in pick.episodes] == [None, None]
    assert [e.failure for e in push.episodes] == ["policy_timeout", "not_run"]
    assert result.abort is not None
    assert "no answer to 'task'" in result.abort.reason
    assert "exit code" not in result.abort.reason  # our own SIGTERM is not reported as its exit
