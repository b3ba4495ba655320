"""Action chunks (protocol 2): negotiated at `hello`, checked whole, executed step by step.

The episode loop is driven by a stand-in environment and channel where counting calls and steps
is what is tested; the SDK runs `serve` on a thread against a real socket; the end-to-end tests
run real policy processes against ManiSkill.
"""

from __future__ import annotations

import shutil
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from evaluator.conditions import ConditionRuntime
from evaluator.episode import chunk_of, run_episode
from evaluator.job import EvaluationJob, evaluation_job
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EpisodeResult, episode_records
from evaluator.suite import (
    ActionChunks,
    ActionDelay,
    Condition,
    LowFreq,
    Nominal,
    ObsNoise,
    Suite,
)
from manieval_sdk import Policy, serve
from manieval_sdk.serve import action_reply, agreed_version, task_spec
from manieval_sdk.wire import recv_message, send_message
from tests.evaluator.conftest import (
    HERE,
    SCRIPTED,
    run,
    tiny_plan,
    tiny_suite,
)

SHAPE = (2,)
BOUNDS = (np.full(SHAPE, -100, np.float32), np.full(SHAPE, 100, np.float32))


def chunked(plan: EvaluationPlan, **chunks: int) -> EvaluationPlan:
    return plan.model_copy(update={"action_chunks": ActionChunks(**chunks)})  # type: ignore[arg-type]


# --- the suite ---------------------------------------------------------------------------------


def test_a_suite_without_chunks_keeps_its_hash_and_one_action_per_call():
    suite = tiny_suite()
    assert suite.action_chunks == ActionChunks(max_length=1)
    assert suite.action_chunks.executed == 1
    with_default = Suite.model_validate({**suite.model_dump(), "action_chunks": {}})
    assert with_default.sha256() == suite.sha256()


def test_chunk_settings_are_part_of_the_hash():
    suite = tiny_suite()
    hashes = {
        suite.model_copy(update={"action_chunks": ActionChunks(**chunks)}).sha256()  # type: ignore[arg-type]
        for chunks in ({}, {"max_length": 8}, {"max_length": 8, "execute": 4})
    }
    assert len(hashes) == 3


def test_execute_defaults_to_the_whole_chunk_and_may_not_exceed_it():
    assert ActionChunks(max_length=16).executed == 16
    assert ActionChunks(max_length=16, execute=8).executed == 8
    with pytest.raises(ValueError, match=r"execute \(9\) exceeds max_length \(8\)"):
        ActionChunks(max_length=8, execute=9)


def test_a_kubernetes_job_rebuilds_the_plan_with_the_suites_chunks():
    text = (HERE / "tiny_suite.yaml").read_text() + "action_chunks: {max_length: 8, execute: 4}\n"
    plan = build_plan(Suite.model_validate(yaml.safe_load(text)), "dev", episodes=2)
    assert plan.action_chunks == ActionChunks(max_length=8, execute=4)
    job = evaluation_job(plan, suite_yaml=text)
    assert EvaluationJob.model_validate_json(job.canonical_json()).plan() == plan


# --- what the evaluator accepts ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("answer", "reason"),
    [
        ({"actions": np.zeros((9, 2), np.float32)}, "a chunk of 9 actions, the suite takes 1 to 8"),
        ({"actions": np.zeros((0, 2), np.float32)}, "a chunk of 0 actions, the suite takes 1 to 8"),
        ({"actions": np.zeros((4, 3), np.float32)}, "shape (4, 3), a chunk for the task is (H, 2)"),
        ({"actions": np.zeros(2, np.float32)}, "shape (2,), a chunk for the task is (H, 2)"),
        ({"actions": np.zeros((1, 4, 2), np.float32)}, "a chunk for the task is (H, 2)"),
        ({"actions": np.zeros((4, 2), bool)}, "actions has dtype bool, a number array is needed"),
        ({"actions": [[0.0, 0.0]]}, "actions must be a number array, got list"),
        ({"actions": np.array([[0, 0], [0, np.nan]])}, "actions contains NaN or infinity"),
        ({"actions": np.array([[0, 0], [np.inf, 0]])}, "actions contains NaN or infinity"),
        ({"action": np.zeros(2), "actions": np.zeros((2, 2))}, "either 'action' or 'actions'"),
        ({}, "action must be a number array, got NoneType"),
    ],
)
def test_a_bad_chunk_is_refused_whole_with_the_reason(answer: dict[str, Any], reason: str):
    problem = chunk_of(answer, SHAPE, 8)
    assert isinstance(problem, str)
    assert reason in problem


def test_one_action_is_a_chunk_of_one_and_a_chunk_is_taken_as_sent():
    one = chunk_of({"action": np.array([0.5, -2.0], np.float32)}, SHAPE, 1)
    assert isinstance(one, np.ndarray)
    assert one.tolist() == [[0.5, -2.0]]  # clipped later, step by step, as before
    actions = np.arange(16, dtype=np.float32).reshape(8, 2)
    taken = chunk_of({"actions": actions}, SHAPE, 8)
    assert isinstance(taken, np.ndarray)
    assert taken.tolist() == actions.tolist()


# --- the episode loop, on a stand-in environment ------------------------------------------------


class CountingEnv:
    """Observations and rewards count the steps taken; the task succeeds and terminates at step
    `ends_at`; the actions applied are kept."""

    def __init__(self, ends_at: int | None = None) -> None:
        self.ends_at = ends_at
        self.applied: list[list[float]] = []
        self.unwrapped = SimpleNamespace()

    def reset(self, seed: int) -> tuple[Any, dict[str, Any]]:
        self.applied = []
        return np.zeros((1, 1), np.float32), {}

    def step(self, action: np.ndarray) -> tuple[Any, ...]:
        self.applied.append(action.tolist())
        steps = len(self.applied)
        done = np.array([steps == self.ends_at])
        obs = np.full((1, 1), steps, np.float32)
        return obs, np.array([float(steps)]), done, np.zeros(1, bool), {"success": done}


class ChunkChannel:
    """A PolicyChannel that answers every `act` with a chunk of `length` actions, each the
    number of the call it answers and its place in the chunk; it keeps what it was shown."""

    policy_time_s = 0.0

    def __init__(self, length: int) -> None:
        self.length = length
        self.seen: list[float] = []

    def start_task(self, spec: dict[str, Any]) -> None:
        pass

    def reset(self, obs: Any, info: dict[str, Any]) -> None:
        self.seen = []

    def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
        meanwhile()
        self.seen.append(float(obs[0]))
        call = len(self.seen)
        chunk = [[call, n] for n in range(self.length)]
        if self.length == 1:
            return {"action": np.array(chunk[0], np.float32)}
        return {"actions": np.array(chunk, np.float32)}


def play(
    channel: ChunkChannel,
    *,
    env: CountingEnv | None = None,
    steps: int = 12,
    condition: Any = None,
    ignore_terminations: bool = False,
    **chunks: int,
) -> tuple[EpisodeResult, CountingEnv]:
    env = env or CountingEnv()
    runtime = ConditionRuntime(Condition(name="c", params=condition or Nominal()))
    result = run_episode(
        env,
        channel,
        runtime,
        index=0,
        seed=5,
        step_limit=steps,
        bounds=BOUNDS,
        ignore_terminations=ignore_terminations,
        chunks=ActionChunks(**chunks),  # type: ignore[arg-type]
    )
    return result, env


def test_a_chunk_is_executed_whole_before_the_policy_is_asked_again():
    channel = ChunkChannel(length=4)
    result, env = play(channel, steps=12, max_length=4)
    assert (result.failure, result.steps) == (None, 12)
    assert channel.seen == [0.0, 4.0, 8.0]  # asked at steps 0, 4 and 8, with the latest obs
    assert env.applied[:5] == [[1, 0], [1, 1], [1, 2], [1, 3], [2, 0]]
    assert result.episode_return == sum(range(1, 13))  # every step's reward, once


def test_execute_below_the_chunk_length_asks_again_after_that_many_steps():
    channel = ChunkChannel(length=8)
    result, env = play(channel, steps=12, max_length=8, execute=3)
    assert result.steps == 12
    assert channel.seen == [0.0, 3.0, 6.0, 9.0]
    assert [a[1] for a in env.applied] == [0, 1, 2] * 4  # the rest of each is dropped


def test_a_shorter_chunk_than_execute_is_executed_whole():
    channel = ChunkChannel(length=2)
    result, _ = play(channel, steps=7, max_length=8)
    assert result.steps == 7
    assert channel.seen == [0.0, 2.0, 4.0, 6.0]


def test_the_step_limit_mid_chunk_ends_the_episode_and_drops_the_rest():
    channel = ChunkChannel(length=5)
    result, env = play(channel, steps=12, max_length=5)
    assert result.steps == 12
    assert len(channel.seen) == 3  # 5 + 5 + 2 of the third chunk
    assert len(env.applied) == 12


def test_termination_mid_chunk_ends_the_episode_and_drops_the_rest():
    channel = ChunkChannel(length=8)
    result, _ = play(channel, env=CountingEnv(ends_at=11), steps=40, max_length=8)
    assert (result.steps, result.success_once, result.failure) == (11, True, None)
    assert len(channel.seen) == 2
    assert result.episode_return == sum(range(1, 12))


def test_with_ignore_terminations_a_chunk_runs_past_a_success():
    channel = ChunkChannel(length=8)
    result, _ = play(
        channel, env=CountingEnv(ends_at=3), steps=8, max_length=8, ignore_terminations=True
    )
    assert (result.steps, result.success_once, result.success_at_end) == (8, True, False)
    assert len(channel.seen) == 1


def test_out_of_bounds_actions_in_a_chunk_are_clipped_and_counted_per_step():
    class Wild(ChunkChannel):
        def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> Any:
            super().act(obs, meanwhile=meanwhile)
            return {"actions": np.array([[0, 0], [500, 0], [0, -500], [0, 0]], np.float32)}

    result, env = play(Wild(length=4), steps=8, max_length=4)
    assert result.clipped_actions == 4
    assert env.applied[:4] == [[0, 0], [100, 0], [0, -100], [0, 0]]


def test_a_bad_chunk_fails_the_episode_before_any_of_it_is_applied():
    class LastIsNaN(ChunkChannel):
        def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> Any:
            super().act(obs, meanwhile=meanwhile)
            chunk = np.zeros((4, 2), np.float32)
            chunk[-1, 0] = np.nan if len(self.seen) == 2 else 0.0
            return {"actions": chunk}

    result, env = play(LastIsNaN(length=4), steps=20, max_length=4)
    assert (result.failure, result.invalid_actions) == ("invalid_action", 1)
    assert result.failure_reason == "actions contains NaN or infinity"
    assert result.steps == len(env.applied) == 4  # the first chunk only


def test_a_chunk_longer_than_the_suite_takes_fails_the_episode():
    result, env = play(ChunkChannel(length=9), steps=20, max_length=8)
    assert result.failure == "invalid_action"
    assert result.failure_reason == "a chunk of 9 actions, the suite takes 1 to 8"
    assert env.applied == []


def test_under_action_delay_each_request_carries_the_observation_k_steps_old():
    channel = ChunkChannel(length=4)
    play(channel, steps=12, max_length=4, condition=ActionDelay(steps=2))
    assert channel.seen == [0.0, 2.0, 6.0]  # as a policy asked at every step would see them


@pytest.mark.parametrize("condition", [ObsNoise(sigma=0.1), ActionDelay(steps=3), LowFreq()])
def test_what_a_chunked_policy_sees_is_what_it_would_see_asked_at_every_step(condition: Any):
    every = ChunkChannel(length=1)
    play(every, steps=12, condition=condition)
    chunks = ChunkChannel(length=4)
    play(chunks, steps=12, max_length=4, condition=condition)
    assert chunks.seen == every.seen[::4]


# --- the SDK ----------------------------------------------------------------------------------

SPEC = {
    "env_id": "PickCube-v1",
    "obs_mode": "state_dict",
    "control_mode": "pd_ee_delta_pose",
    "control_freq": 20,
    "max_episode_steps": 50,
    "action_space": {"low": -np.ones(2, np.float32), "high": np.ones(2, np.float32)},
}


def spec_with(**chunks: int) -> dict[str, Any]:
    return {**SPEC, "action_chunks": chunks}


@pytest.mark.parametrize(("offered", "agreed"), [(1, 1), (2, 2), (3, 2), (None, 1), (True, 1)])
def test_the_sdk_speaks_the_lower_of_both_sides_newest_version(offered: Any, agreed: int):
    assert agreed_version(offered) == agreed


def test_the_sdk_reads_the_chunk_settings_and_defaults_to_one_action():
    assert task_spec(spec_with(max_length=16, execute=8)).action_chunks.execute == 8
    assert task_spec(spec_with(max_length=16, execute=8)).action_chunks.max_length == 16
    assert task_spec(SPEC).action_chunks.execute == 1  # a protocol 1 evaluator sends none


def test_the_sdk_sends_the_actions_that_are_executed_and_one_action_alone():
    spec = task_spec(spec_with(max_length=16, execute=8))
    chunk = np.arange(20, dtype=np.float32).reshape(10, 2)
    sent = action_reply(chunk, spec, protocol=2)
    assert set(sent) == {"type", "actions"}
    assert sent["actions"].tolist() == chunk[:8].tolist()
    single = action_reply([0.5, 0.5], spec, protocol=2)
    assert set(single) == {"type", "action"}
    assert single["action"].tolist() == [0.5, 0.5]


@pytest.mark.parametrize(
    ("spec", "protocol"),
    [(spec_with(max_length=16, execute=8), 1), (spec_with(max_length=1, execute=1), 2)],
    ids=["protocol-1", "no-chunks-in-the-suite"],
)
def test_where_chunks_are_not_taken_the_sdk_sends_the_first_action(
    spec: dict[str, Any], protocol: int
):
    chunk = np.arange(20, dtype=np.float32).reshape(10, 2)
    sent = action_reply(chunk, task_spec(spec), protocol=protocol)
    assert set(sent) == {"type", "action"}
    assert sent["action"].tolist() == [0.0, 1.0]


def test_an_empty_chunk_is_the_policys_error():
    with pytest.raises(ValueError, match="empty chunk"):
        action_reply(np.zeros((0, 2)), task_spec(spec_with(max_length=8, execute=8)), protocol=2)


class Planner(Policy):
    """Answers with a chunk of 10 actions."""

    def act(self, obs: Any) -> np.ndarray:
        return np.tile(np.arange(10, dtype=np.float32)[:, None], (1, 2))


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Callable[[int], socket.socket]]:
    """`serve(Planner())` on a thread; connected and greeted with the given version."""
    started: list[tuple[socket.socket, threading.Thread]] = []

    def start(offered: int) -> socket.socket:
        path = tmp_path / f"policy{len(started)}.sock"
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(str(path))
        listener.listen(1)
        thread = threading.Thread(target=serve, args=(Planner(), f"unix://{path}"), daemon=True)
        thread.start()
        conn, _ = listener.accept()
        listener.close()
        started.append((conn, thread))
        send_message(conn, {"type": "hello", "protocol": offered})
        return conn

    yield start
    for conn, thread in started:
        send_message(conn, {"type": "close"})
        thread.join(10)
        conn.close()


def answer(conn: socket.socket, message: dict[str, Any]) -> dict[str, Any]:
    send_message(conn, message)
    return recv_message(conn, deadline=time.monotonic() + 60)


@pytest.mark.parametrize(("offered", "sent"), [(2, {"actions": (6, 2)}), (1, {"action": (2,)})])
def test_a_served_policy_sends_chunks_only_where_the_evaluator_speaks_protocol_2(
    served: Callable[[int], socket.socket], offered: int, sent: dict[str, tuple[int, ...]]
):
    conn = served(offered)
    assert recv_message(conn, deadline=time.monotonic() + 60)["protocol"] == offered
    assert answer(conn, {"type": "task", "spec": spec_with(max_length=8, execute=6)}) == {
        "type": "ok"
    }
    reply = answer(conn, {"type": "act", "obs": np.zeros(1)})
    assert {name: value.shape for name, value in reply.items() if name != "type"} == sent


# --- end to end, real policy processes and ManiSkill -------------------------------------------

PLANNER = """
import numpy as np
from manieval_sdk import serve
from scripted import ScriptedPolicy

H = 8

class Planner(ScriptedPolicy):
    def plan(self, obs):
        # Deterministic: the scripted controller run H times on the one observation.
        return np.stack([ScriptedPolicy.act(self, obs) for _ in range(H)])

class Chunked(Planner):
    def act(self, obs):
        return self.plan(obs)

class OneByOne(Planner):
    def reset(self, obs, info):
        super().reset(obs, info)
        self.queue = []

    def act(self, obs):
        if not self.queue:
            self.queue = list(self.plan(obs))
        return self.queue.pop(0)

serve(POLICY())
"""


@pytest.fixture
def planner(make_policy: Callable[[str], Path]) -> Callable[[str], Path]:
    def write(policy: str) -> Path:
        directory = make_policy(PLANNER.replace("POLICY", policy))
        shutil.copy(SCRIPTED / "policy.py", directory / "scripted.py")
        return directory

    return write


def longer_nominal_pick(plan: EvaluationPlan, steps: int) -> EvaluationPlan:
    """The plan with PickCube-v1's nominal episodes long enough for the scripted policy."""
    runs = tuple(
        run.model_copy(update={"max_episode_steps": steps})
        if (run.env_id, run.condition.name) == ("PickCube-v1", "nominal")
        else run
        for run in plan.runs
    )
    return plan.model_copy(update={"runs": runs})


@pytest.mark.sim
def test_a_chunked_policy_and_the_same_policy_step_by_step_record_identical_episodes(
    planner: Callable[[str], Path],
):
    plan = chunked(longer_nominal_pick(tiny_plan(episodes=1), 70), max_length=8)
    one_by_one = run(plan, planner("OneByOne"))
    chunks = run(plan, planner("Chunked"))
    assert one_by_one.status == chunks.status == "completed"
    records = episode_records(chunks)
    assert records == episode_records(one_by_one)
    assert {r["failure"] for r in records} == {None}
    assert {r["condition"] for r in records} == {"nominal", "obs_noise", "action_delay", "low_freq"}
    assert any(r["success_once"] for r in records)  # PickCube-v1 nominal, in 60 steps


RAW_POLICY = """
import os
import numpy as np
from manieval_sdk.serve import connect
from manieval_sdk.wire import encode_frame, recv_message

VERSION = {version}
ANSWERS = {answers}
sock = connect(os.environ["MANIEVAL_ENDPOINT"])
episode = 0
while True:
    message = recv_message(sock)
    kind = message["type"]
    if kind == "close":
        break
    reply = {{"type": "ok"}}
    if kind == "hello":
        reply = {{"type": "ready", "protocol": VERSION}}
    elif kind == "reset":
        episode = message["info"]["episode"]
    elif kind == "act":
        reply = {{"type": "action", **ANSWERS[episode % len(ANSWERS)]}}
    sock.sendall(encode_frame(reply))
"""


@pytest.mark.sim
def test_bad_chunks_on_the_wire_fail_their_episodes_and_the_evaluation_goes_on(
    make_policy: Callable[[str], Path],
):
    answers = """[
        {"actions": np.zeros((9, 7), np.float32)},
        {"actions": np.zeros((8, 3), np.float32)},
        {"actions": np.concatenate([np.zeros((7, 7)), np.full((1, 7), np.nan)])},
        {"actions": np.zeros(7, np.float32)},
        {"action": np.zeros(7, np.float32), "actions": np.zeros((2, 7), np.float32)},
        {"actions": np.zeros((8, 7), np.float32)},
    ]"""
    plan = chunked(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=6), max_length=8
    )
    result = run(plan, make_policy(RAW_POLICY.format(version=2, answers=answers)))
    assert result.status == "completed"
    episodes = result.conditions[0].tasks[0].episodes
    assert [(e.failure, e.failure_reason, e.steps) for e in episodes] == [
        ("invalid_action", "a chunk of 9 actions, the suite takes 1 to 8", 0),
        ("invalid_action", "actions has shape (8, 3), a chunk for the task is (H, 7)", 0),
        ("invalid_action", "actions contains NaN or infinity", 0),
        ("invalid_action", "actions has shape (7,), a chunk for the task is (H, 7)", 0),
        ("invalid_action", "an answer carries either 'action' or 'actions', not both", 0),
        (None, None, 12),
    ]


@pytest.mark.sim
def test_a_protocol_1_policy_works_unchanged_where_chunks_are_taken(
    make_policy: Callable[[str], Path],
):
    # Protocol 1 knows no `actions`: ignored like any other field it does not know.
    answers = '[{"action": np.zeros(7, np.float32), "actions": np.zeros((8, 7), np.float32)}]'
    plan = chunked(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1), max_length=8
    )
    result = run(plan, make_policy(RAW_POLICY.format(version=1, answers=answers)))
    assert [(e.failure, e.steps) for e in result.conditions[0].tasks[0].episodes] == [(None, 12)]
