"""Protocol overhead: the same policy and seeds, called in-process vs over the wire protocol.

Prints steps/s of both and their ratio for state and rgb observations. Rounds alternate between
the two so that machine noise hits both alike; the ratio of the medians is the figure to read.

    .venv/bin/python bench/protocol_overhead.py [--rounds 3] [--episodes 4] [--steps 50]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluator.channel import InProcessChannel, PolicyChannel, RemoteChannel  # noqa: E402
from evaluator.endpoint import PolicyEndpoint  # noqa: E402
from evaluator.plan import EvaluationPlan, build_plan  # noqa: E402
from evaluator.runner import RunOptions, ShardOutcome, run_units  # noqa: E402
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


def steps_per_second(plan: EvaluationPlan, channel: PolicyChannel) -> float:
    outcome = ShardOutcome()
    units = [(0, tuple(enumerate(plan.runs[0].seeds)))]
    options = RunOptions()
    run_units(plan, channel, units, outcome, options=options, on_episode=lambda _r, _e: None)
    episodes = [e for _, e in outcome.episodes]
    assert all(e.failure is None for e in episodes), episodes
    return sum(e.steps for e in episodes) / sum(e.wall_time_s for e in episodes)


def in_process_channel() -> InProcessChannel:
    spec = importlib.util.spec_from_file_location("zero_policy", POLICY_DIR / "policy.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return InProcessChannel(module.Zero())


def measure(obs_mode: str, rounds: int, episodes: int, steps: int) -> tuple[float, float]:
    plan = plan_for(obs_mode, episodes, steps)
    endpoint = PolicyEndpoint(max_frame_bytes=plan.limits.max_action_frame_bytes)
    process = LocalDirectory(POLICY_DIR).launch(
        endpoint=endpoint.address, socket_dir=endpoint.socket_dir
    )
    try:
        endpoint.accept(timeout=60, alive=process.alive)
        endpoint.hello(timeout=60)
        remote = RemoteChannel(endpoint, plan.limits)
        local = in_process_channel()
        local_rates, remote_rates = [], []
        for _ in range(rounds):
            local_rates.append(steps_per_second(plan, local))
            remote_rates.append(steps_per_second(plan, remote))
    finally:
        endpoint.close()
        process.stop()
    return statistics.median(local_rates), statistics.median(remote_rates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--rgb-steps", type=int, default=10)
    args = parser.parse_args()
    print(f"{'obs_mode':<12}{'in-process steps/s':>20}{'protocol steps/s':>18}{'ratio':>8}")
    for obs_mode, steps in (("state_dict", args.steps), ("rgb", args.rgb_steps)):
        local, remote = measure(obs_mode, args.rounds, args.episodes, steps)
        print(f"{obs_mode:<12}{local:>20.1f}{remote:>18.1f}{remote / local:>8.3f}")


if __name__ == "__main__":
    main()
