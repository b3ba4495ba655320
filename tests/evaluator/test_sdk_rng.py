"""The SDK's reproducible randomness: one generator per episode, the global generators reseeded.

The policy side runs `serve` on a thread against a real Unix socket, as the evaluator drives it.
"""

from __future__ import annotations

import hashlib
import random
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from evaluator.results import episode_records
from manieval_sdk import Policy, episode_seed, serve
from manieval_sdk.wire import recv_message, send_message
from tests.evaluator.conftest import run, tiny_plan

SPEC = {
    "env_id": "PickCube-v1",
    "obs_mode": "state_dict",
    "control_mode": "pd_ee_delta_pose",
    "control_freq": 20,
    "max_episode_steps": 50,
    "action_space": {"low": -np.ones(5, np.float32), "high": np.ones(5, np.float32)},
}


def observation(x: float = 0.5) -> dict[str, Any]:
    return {
        "agent": {"qpos": np.full(9, x, dtype=np.float32), "qvel": np.zeros(9, np.float32)},
        "extra": {"tcp_pose": np.arange(7, dtype=np.float32), "is_grasped": np.array(False)},
    }


class Draws(Policy):
    """Answers every act with one draw from each generator a policy might use."""

    def act(self, obs: Any) -> np.ndarray:
        return np.array(
            [
                self.rng.random(),
                random.random(),
                np.random.random(),
                torch.rand(1).item(),
                np.random.normal(),  # a naive policy: numpy's global generator, never seeded
            ]
        )


class OwnSeeding(Draws):
    seed_globals = False


class PolicyConnection:
    """The evaluator's end of a connection to a policy served on a thread."""

    def __init__(self, conn: socket.socket, thread: threading.Thread) -> None:
        self.conn = conn
        self.thread = thread

    def call(self, message: dict[str, Any]) -> dict[str, Any]:
        send_message(self.conn, message)
        return recv_message(self.conn, deadline=time.monotonic() + 120)

    def episode(self, obs: dict[str, Any], *, steps: int = 2) -> list[list[float]]:
        """Reset with `obs`, then act `steps` times; the draws of each step."""
        assert self.call({"type": "reset", "obs": obs, "index": 0})["type"] == "ok"
        return [self.call({"type": "act", "obs": obs})["action"].tolist() for _ in range(steps)]


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Any]:
    connections: list[PolicyConnection] = []

    def start(policy: Policy) -> PolicyConnection:
        path = tmp_path / f"policy{len(connections)}.sock"
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(str(path))
        listener.listen(1)
        thread = threading.Thread(target=serve, args=(policy, f"unix://{path}"), daemon=True)
        thread.start()
        conn, _ = listener.accept()
        listener.close()
        connection = PolicyConnection(conn, thread)
        connections.append(connection)
        assert connection.call({"type": "hello", "protocol": 1})["type"] == "ready"
        assert connection.call({"type": "task", "spec": SPEC})["type"] == "ok"
        return connection

    yield start
    for connection in connections:
        send_message(connection.conn, {"type": "close"})
        connection.thread.join(10)
        connection.conn.close()


def test_the_seed_is_the_documented_hash_of_the_first_observation():
    obs = {"b": np.array([1.5, -2.0], dtype=np.float32), "a": {"c": np.array(3, dtype=np.int64)}}
    canonical = b"a" + b"c" + b"<i8(1,)" + (3).to_bytes(8, "little")  # 0-d: as shape (1,)
    canonical += b"b" + b"<f4(2,)" + np.array([1.5, -2.0], dtype="<f4").tobytes()
    digest = hashlib.sha256(canonical).digest()
    assert episode_seed(obs) == int.from_bytes(digest[:8], "little")
    assert episode_seed(obs) == 0x7783A1DDA01CA6B2  # the worked example of docs/protocol.md


def test_identical_first_observations_give_identical_generators(served):
    first, second = served(Draws()), served(Draws())
    first.episode(observation(0.1))  # what ran before must not matter
    assert first.episode(observation()) == second.episode(observation())


def test_the_seed_is_the_same_in_another_process():
    script = (
        "import numpy as np; from manieval_sdk import episode_seed;"
        "print(episode_seed({'q': np.arange(4, dtype=np.float32), 'g': np.array(True)}))"
    )
    other = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True
    )
    obs = {"q": np.arange(4, dtype=np.float32), "g": np.array(True)}
    assert int(other.stdout) == episode_seed(obs)


@pytest.mark.parametrize(
    "changed",
    [
        observation(0.5000001),
        {**observation(), "extra": {**observation()["extra"], "is_grasped": np.array(True)}},
        {**observation(), "agent": {"qpos": np.full(9, 0.5, np.float64)}},  # same values, f8
        {"agent2": observation()["agent"], "extra": observation()["extra"]},  # another key
    ],
    ids=["value", "flag", "dtype", "key"],
)
def test_different_first_observations_give_different_generators(served, changed):
    policy = served(Draws())
    assert episode_seed(changed) != episode_seed(observation())
    assert policy.episode(changed) != policy.episode(observation())


def test_the_global_generators_are_seeded_at_each_reset(served):
    policy = served(Draws())
    before = policy.episode(observation(0.2), steps=3)
    random.random()  # someone else draws in between
    np.random.random()
    torch.rand(3)
    policy.episode(observation(0.7), steps=5)
    again = policy.episode(observation(0.2), steps=3)
    assert again == before
    rng, py, np_global, torch_draw, _naive = zip(*before, strict=True)
    assert len({*py, *np_global, *torch_draw, *rng}) == 12  # four distinct streams


def test_a_policy_may_keep_the_global_generators_to_itself(served):
    policy = served(OwnSeeding())
    random.seed(7)
    np.random.seed(7)
    expected = (random.random(), np.random.random())
    random.seed(7)
    np.random.seed(7)
    draws = policy.episode(observation(), steps=1)[0]
    assert (draws[1], draws[2]) == expected


def test_the_task_seeds_the_generators_for_setup(served):
    seen: list[float] = []

    class DrawsInSetup(Draws):
        def setup(self, spec: Any) -> None:
            super().setup(spec)
            seen.extend([self.rng.random(), np.random.random()])

    served(DrawsInSetup())
    np.random.random()
    served(DrawsInSetup())
    assert seen[:2] == seen[2:]


def test_torch_is_seeded_only_when_the_policy_imported_it():
    script = """
import sys, numpy as np
from manieval_sdk.seeding import seed_global_generators
seed_global_generators(12345)
print("torch" in sys.modules)
"""
    other = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True
    )
    assert other.stdout.strip() == "False"


NAIVE_POLICY = """
import numpy as np
from manieval_sdk import Policy, serve

class Naive(Policy):
    def act(self, obs):
        return np.random.uniform(-1, 1, self.spec.action_shape).astype(np.float32)

serve(Naive())
"""


@pytest.mark.sim
def test_a_naive_stochastic_policy_scores_the_same_with_one_and_three_workers(make_policy):
    directory = make_policy(NAIVE_POLICY)
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal", "obs_noise"], episodes=3)
    one, three = run(plan, directory), run(plan, directory, workers=3)
    assert one.status == three.status == "completed"
    assert episode_records(one) == episode_records(three)
