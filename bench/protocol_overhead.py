"""Protocol overhead: the same policy and seeds, called in-process vs over the wire protocol.

Prints steps/s of both and their ratio for state and rgb (128x128) observations. Each path
keeps its own environment and the two take turns episode by episode (the same seed for both,
in alternating order), so that what else the machine does hits both alike: a run of seconds
on one path would meet another load than the other's. The ratio is of all the rounds' steps/s
together, with the spread of the rounds' own ratios beside it, and what the protocol adds to
each step in microseconds; then the floor under that on this machine, a bare round trip
between two processes (bench/socket_round_trip.py). The last line is
`protocol_state_ratio <ratio>` (the aim: 0.97 for state, 0.95 for rgb).

    .venv/bin/python bench/protocol_overhead.py [--rounds 9] [--episodes 6] [--steps 100]
        [--rgb-episodes 4] [--rgb-steps 20]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluator.channel import InProcessChannel, PolicyChannel, RemoteChannel  # noqa: E402
from evaluator.endpoint import PolicyEndpoint  # noqa: E402
from evaluator.episode import run_episode  # noqa: E402
from evaluator.plan import EvaluationPlan, build_plan  # noqa: E402
from evaluator.runner import RunOptions, open_task, task_spec  # noqa: E402
from evaluator.sim import action_bounds, default_control_freq  # noqa: E402
from evaluator.sources import LocalDirectory  # noqa: E402
from evaluator.suite import load_suite  # noqa: E402

POLICY_DIR = Path(__file__).parent / "zero_policy"


def plan_for(obs_mode: str, episodes: int, steps: int) -> EvaluationPlan:
    plan = build_plan(
        load_suite("maniskill-core"),
        "dev",
        tasks=["PickCube-v1"],
        conditions=["nominal"],
        episodes=episodes,
    )
    run = plan.runs[0].model_copy(update={"obs_mode": obs_mode, "max_episode_steps": steps})
    return plan.model_copy(update={"runs": (run,)})


class PolicyPath:
    """One way of calling the policy, with its own environment."""

    def __init__(self, plan: EvaluationPlan, channel: PolicyChannel) -> None:
        self.channel = channel
        self.task = open_task(plan, 0, tuple(enumerate(plan.runs[0].seeds)), RunOptions())
        run = plan.runs[0]
        self.step_limit = self.task.runtime.step_limit(
            run.max_episode_steps, default_control_freq(self.task.env)
        )
        channel.start_task(task_spec(run, self.task.env, self.step_limit))
        self.ignore_terminations = plan.ignore_terminations

    def episode(self, seed: int) -> tuple[int, float]:
        """Play one episode; its steps and wall time."""
        result = run_episode(
            self.task.env,
            self.channel,
            self.task.runtime,
            index=0,
            seed=seed,
            step_limit=self.step_limit,
            bounds=action_bounds(self.task.env),
            ignore_terminations=self.ignore_terminations,
        )
        assert result.failure is None, result
        return result.steps, result.wall_time_s

    def close(self) -> None:
        self.task.env.close()


def in_process_channel() -> InProcessChannel:
    spec = importlib.util.spec_from_file_location("zero_policy", POLICY_DIR / "policy.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return InProcessChannel(module.Zero())


def measure(
    obs_mode: str, rounds: int, episodes: int, steps: int
) -> tuple[float, float, list[float]]:
    """Steps/s in-process and over the protocol (all rounds together), and each round's ratio."""
    plan = plan_for(obs_mode, episodes, steps)
    endpoint = PolicyEndpoint(max_frame_bytes=plan.limits.max_action_frame_bytes)
    process = LocalDirectory(POLICY_DIR).launch(
        endpoint=endpoint.address, socket_dir=endpoint.socket_dir
    )
    try:
        endpoint.accept(timeout=60, alive=process.alive)
        endpoint.hello(timeout=60)
        paths = [
            PolicyPath(plan, in_process_channel()),
            PolicyPath(plan, RemoteChannel(endpoint, plan.limits)),
        ]
        try:
            for path in paths:  # warm both (first calls, first episode) before measuring
                path.episode(plan.runs[0].seeds[0])
            totals = [[0, 0.0], [0, 0.0]]  # steps and seconds of each path, all rounds
            ratios = []
            for round_no in range(rounds):
                rates = [[0, 0.0], [0, 0.0]]
                for n, seed in enumerate(plan.runs[0].seeds):
                    for which in (0, 1) if (round_no + n) % 2 == 0 else (1, 0):
                        steps, seconds = paths[which].episode(seed)
                        for tally in (rates[which], totals[which]):
                            tally[0] += steps
                            tally[1] += seconds
                local, remote = (steps / seconds for steps, seconds in rates)
                ratios.append(remote / local)
        finally:
            for path in paths:
                path.close()
    finally:
        endpoint.close()
        process.stop()
    local_rate, remote_rate = (steps / seconds for steps, seconds in totals)
    return local_rate, remote_rate, ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rgb-episodes", type=int, default=4)
    parser.add_argument("--rgb-steps", type=int, default=20)
    args = parser.parse_args()
    head = f"{'obs_mode':<12}{'in-process steps/s':>20}{'protocol steps/s':>18}{'ratio':>8}"
    print(head + f"{'us/step':>9}  rounds' ratios (min-max)")
    figures = {}
    for obs_mode, episodes, steps in (
        ("state_dict", args.episodes, args.steps),
        ("rgb", args.rgb_episodes, args.rgb_steps),
    ):
        local, remote, ratios = measure(obs_mode, args.rounds, episodes, steps)
        figures[obs_mode] = ratio = remote / local
        overhead_us = (1 / remote - 1 / local) * 1e6
        print(
            f"{obs_mode:<12}{local:>20.1f}{remote:>18.1f}{ratio:>8.3f}{overhead_us:>9.0f}"
            f"  {min(ratios):.3f}-{max(ratios):.3f}"
        )
    floor = subprocess.run(
        [sys.executable, str(Path(__file__).parent / "socket_round_trip.py")],
        capture_output=True,
        text=True,
        check=True,
    )
    print("us/step: what the protocol adds to a step. The floor under it on this machine,")
    print(floor.stdout.splitlines()[0])
    print(f"protocol_state_ratio {figures['state_dict']:.3f}")


if __name__ == "__main__":
    main()
