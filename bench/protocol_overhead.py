"""Protocol overhead: the same policy and seeds, called in-process vs over the wire protocol.

Prints steps/s of both and their ratio for each kind of observation the protocol carries: state,
rgb and rgbd at 128x128 (the tabletop tasks' camera), rgbd at 224x224 (through ManiSkill's
`sensor_configs`), pointcloud, and state again with a policy that answers with chunks of 8
actions (protocol 2). Each path keeps its own environment and the two take turns episode by
episode (the same seed for both, in alternating order), so that what else the machine does hits
both alike: a run of seconds on one path would meet another load than the other's. The ratio is
of all the rounds' steps/s together, with the spread of the rounds' own ratios beside it, what
the protocol adds to each step in microseconds (per step: a chunk's call is shared by its
steps), and the median of the pairs' ratios (a pair: the two paths on one seed, one after the
other; the figure least moved by bursts of load from elsewhere). Last, the fastest of
`--calls` answers to one observation on each path, their difference per step (the protocol's own
cost at best: on a loaded machine the figure that load moves least) and the ratio that cost
would give against the fastest in-process episode's steps/s. Then the floor under all this on this
machine, a bare round trip between two processes
(bench/socket_round_trip.py). One line `protocol_<row>_ratio <ratio>` per row follows, the last
`protocol_state_ratio <ratio>` (the aims: 0.97 for state, 0.95 for camera observations, 0.99
for chunks).

    .venv/bin/python bench/protocol_overhead.py [--rounds 9] [--episodes 6] [--steps 100]
        [--rgb-episodes 4] [--rgb-steps 20] [--calls 300]
        [--rows state,rgb,rgbd,rgbd224,pointcloud,chunks8]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluator.channel import InProcessChannel, PolicyChannel, RemoteChannel  # noqa: E402
from evaluator.conditions import ConditionRuntime  # noqa: E402
from evaluator.endpoint import PolicyEndpoint  # noqa: E402
from evaluator.episode import run_episode  # noqa: E402
from evaluator.plan import EvaluationPlan, build_plan  # noqa: E402
from evaluator.runner import task_spec  # noqa: E402
from evaluator.sim import action_bounds, default_control_freq, make_env, to_numpy  # noqa: E402
from evaluator.sources import LocalDirectory  # noqa: E402
from evaluator.suite import NO_CHUNKS, ActionChunks, Condition, load_suite  # noqa: E402

POLICY_DIR = Path(__file__).parent / "zero_policy"


@dataclass(frozen=True)
class Row:
    """What one row measures: the observation mode, the camera's side (None: the task's own,
    128 pixels), and the chunks the policy answers with."""

    name: str
    obs_mode: str
    camera: int | None = None
    chunks: ActionChunks = NO_CHUNKS
    renders: bool = True  # camera frames at every step: slow, so fewer episodes and steps

    def plan(self, args: argparse.Namespace) -> EvaluationPlan:
        episodes, steps = (
            (args.rgb_episodes, args.rgb_steps) if self.renders else (args.episodes, args.steps)
        )
        plan = build_plan(
            load_suite("maniskill-core"),
            "dev",
            tasks=["PickCube-v1"],
            conditions=["nominal"],
            episodes=episodes,
        )
        run = plan.runs[0].model_copy(
            update={"obs_mode": self.obs_mode, "max_episode_steps": steps}
        )
        return plan.model_copy(update={"runs": (run,), "action_chunks": self.chunks})


ROWS = (
    Row("state", "state_dict", renders=False),
    Row("rgb", "rgb"),
    Row("rgbd", "rgbd"),
    Row("rgbd224", "rgbd", camera=224),
    Row("pointcloud", "pointcloud"),
    Row("chunks8", "state_dict", chunks=ActionChunks(max_length=8), renders=False),
)


class CameraRuntime(ConditionRuntime):
    """A condition that also sets the side of the task's sensor cameras, in pixels."""

    def __init__(self, condition: Condition, side: int) -> None:
        super().__init__(condition)
        self._side = side

    def env_kwargs(self) -> dict[str, Any]:
        camera = {"width": self._side, "height": self._side}
        return {**super().env_kwargs(), "sensor_configs": camera}


class PolicyPath:
    """One way of calling the policy, with its own environment."""

    def __init__(self, plan: EvaluationPlan, row: Row, channel: PolicyChannel) -> None:
        self.channel = channel
        run = plan.runs[0]
        self.runtime = (
            CameraRuntime(run.condition, row.camera)
            if row.camera
            else ConditionRuntime(run.condition)
        )
        self.env = make_env(run, self.runtime)
        self.step_limit = self.runtime.step_limit(
            run.max_episode_steps, default_control_freq(self.env)
        )
        self.chunks = plan.action_chunks
        channel.start_task(task_spec(run, self.env, self.step_limit, self.chunks))
        self.ignore_terminations = plan.ignore_terminations

    def episode(self, seed: int) -> tuple[int, float]:
        """Play one episode; its steps and wall time."""
        result = run_episode(
            self.env,
            self.channel,
            self.runtime,
            index=0,
            seed=seed,
            step_limit=self.step_limit,
            bounds=action_bounds(self.env),
            ignore_terminations=self.ignore_terminations,
            chunks=self.chunks,
        )
        assert result.failure is None, result
        return result.steps, result.wall_time_s

    def fastest_call(self, seed: int, calls: int) -> float:
        """The shortest of `calls` answers to one observation, in seconds: what the channel
        costs at best, when nothing else on the machine gets in the way."""
        obs = to_numpy(self.env.reset(seed=seed)[0])
        fastest = float("inf")
        for _ in range(calls):
            started = time.perf_counter()
            self.channel.act(obs)
            fastest = min(fastest, time.perf_counter() - started)
        return fastest

    def close(self) -> None:
        self.env.close()


def in_process_channel() -> InProcessChannel:
    spec = importlib.util.spec_from_file_location("zero_policy", POLICY_DIR / "policy.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return InProcessChannel(module.Zero())


@dataclass
class Tally:
    """Steps and seconds of both paths (in-process, protocol), over all rounds; each round's
    ratio; and the ratio of each pair of episodes, the two paths on one seed one after the other."""

    steps: list[int] = field(default_factory=lambda: [0, 0])
    seconds: list[float] = field(default_factory=lambda: [0.0, 0.0])
    rounds: list[float] = field(default_factory=list)
    pairs: list[float] = field(default_factory=list)
    fastest_calls: list[float] = field(default_factory=lambda: [0.0, 0.0])  # seconds, each path
    fastest_local_rate: float = 0.0  # steps/s of the fastest in-process episode

    def rates(self) -> tuple[float, float]:
        """Steps/s in-process and over the protocol."""
        return self.steps[0] / self.seconds[0], self.steps[1] / self.seconds[1]


def measure(row: Row, args: argparse.Namespace) -> Tally:
    """Both paths, episode by episode in turns, over all rounds."""
    plan = row.plan(args)
    endpoint = PolicyEndpoint(max_frame_bytes=plan.limits.max_action_frame_bytes)
    process = LocalDirectory(POLICY_DIR).launch(
        endpoint=endpoint.address, socket_dir=endpoint.socket_dir
    )
    try:
        endpoint.accept(timeout=60, alive=process.alive)
        endpoint.hello(timeout=60)
        paths = [
            PolicyPath(plan, row, in_process_channel()),
            PolicyPath(plan, row, RemoteChannel(endpoint, plan.limits)),
        ]
        try:
            for path in paths:  # warm both (first calls, first episode) before measuring
                path.episode(plan.runs[0].seeds[0])
            tally = Tally()
            for round_no in range(args.rounds):
                play_round(paths, plan.runs[0].seeds, round_no, tally)
            seed = plan.runs[0].seeds[0]
            tally.fastest_calls = [path.fastest_call(seed, args.calls) for path in paths]
        finally:
            for path in paths:
                path.close()
    finally:
        endpoint.close()
        process.stop()
    return tally


def play_round(
    paths: list[PolicyPath], seeds: tuple[int, ...], round_no: int, tally: Tally
) -> None:
    """One episode of each path on every seed, the first path alternating."""
    this_round = Tally()
    for n, seed in enumerate(seeds):
        pair = [0.0, 0.0]  # steps/s of each path on this seed
        for which in (0, 1) if (round_no + n) % 2 == 0 else (1, 0):
            steps, seconds = paths[which].episode(seed)
            pair[which] = steps / seconds
            for counts in (this_round, tally):
                counts.steps[which] += steps
                counts.seconds[which] += seconds
        tally.pairs.append(pair[1] / pair[0])
        tally.fastest_local_rate = max(tally.fastest_local_rate, pair[0])
    local, remote = this_round.rates()
    tally.rounds.append(remote / local)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rgb-episodes", type=int, default=4)
    parser.add_argument("--rgb-steps", type=int, default=20)
    parser.add_argument("--calls", type=int, default=300, help="calls timed for the fastest")
    names = [row.name for row in ROWS]
    parser.add_argument("--rows", default=",".join(names), help="which rows, comma-separated")
    args = parser.parse_args()
    wanted = args.rows.split(",")
    if unknown := sorted(set(wanted) - set(names)):
        parser.error(f"unknown rows {', '.join(unknown)} (there are: {', '.join(names)})")
    head = f"{'row':<12}{'in-process steps/s':>20}{'protocol steps/s':>18}{'ratio':>8}"
    print(
        head + f"{'us/step':>9}  rounds' ratios (min-max)  pairs' median"
        "  fastest call: us/step  ratio",
        flush=True,
    )
    figures = {}
    for row in (row for row in ROWS if row.name in wanted):
        tally = measure(row, args)
        local, remote = tally.rates()
        figures[row.name] = ratio = remote / local
        overhead_us = (1 / remote - 1 / local) * 1e6
        # What the protocol adds to a call at best, shared by the steps of a chunk; and the
        # ratio it would give against the fastest in-process episode: both as on a quiet machine.
        fastest_s = (tally.fastest_calls[1] - tally.fastest_calls[0]) / row.chunks.executed
        best_ratio = 1 / (1 + fastest_s * tally.fastest_local_rate)
        print(
            f"{row.name:<12}{local:>20.1f}{remote:>18.1f}{ratio:>8.3f}{overhead_us:>9.0f}"
            f"  {min(tally.rounds):.3f}-{max(tally.rounds):.3f}"
            f"{statistics.median(tally.pairs):>22.3f}"
            f"{fastest_s * 1e6:>24.0f}{best_ratio:>7.3f}",
            flush=True,
        )
    floor = subprocess.run(
        [sys.executable, str(Path(__file__).parent / "socket_round_trip.py")],
        capture_output=True,
        text=True,
        check=True,
    )
    print("us/step: what the protocol adds to a step. The floor under it on this machine,")
    print(floor.stdout.splitlines()[0])
    for name in sorted(figures, key=lambda name: name == "state"):  # the state row's last
        print(f"protocol_{name}_ratio {figures[name]:.3f}")


if __name__ == "__main__":
    main()
