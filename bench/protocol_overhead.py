"""Protocol overhead: the same policy and seeds, called in-process vs over the wire protocol.

Prints steps/s of both and their ratio for state and rgb (128x128) observations. Each round
measures both, in alternating order, back to back, so that what else the machine does hits
both alike; the figure is the median of the rounds' ratios, with their spread beside it. The
last line is `protocol_state_ratio <ratio>` (the aim: 0.97 for state, 0.95 for rgb).

    .venv/bin/python bench/protocol_overhead.py [--rounds 9] [--episodes 6] [--steps 100]
        [--rgb-episodes 4] [--rgb-steps 20]
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


def measure(
    obs_mode: str, rounds: int, episodes: int, steps: int
) -> tuple[float, float, list[float]]:
    """Median steps/s in-process and over the protocol, and each round's ratio."""
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
        steps_per_second(plan, local)  # warm both (first env, first calls) before measuring
        steps_per_second(plan, remote)
        local_rates, remote_rates = [], []
        for round_no in range(rounds):
            if round_no % 2:
                remote_rates.append(steps_per_second(plan, remote))
                local_rates.append(steps_per_second(plan, local))
            else:
                local_rates.append(steps_per_second(plan, local))
                remote_rates.append(steps_per_second(plan, remote))
    finally:
        endpoint.close()
        process.stop()
    ratios = [r / loc for loc, r in zip(local_rates, remote_rates, strict=True)]
    return statistics.median(local_rates), statistics.median(remote_rates), ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rgb-episodes", type=int, default=4)
    parser.add_argument("--rgb-steps", type=int, default=20)
    args = parser.parse_args()
    head = f"{'obs_mode':<12}{'in-process steps/s':>20}{'protocol steps/s':>18}{'ratio':>8}"
    print(head + "  rounds' ratios (min-max)")
    figures = {}
    for obs_mode, episodes, steps in (
        ("state_dict", args.episodes, args.steps),
        ("rgb", args.rgb_episodes, args.rgb_steps),
    ):
        local, remote, ratios = measure(obs_mode, args.rounds, episodes, steps)
        figures[obs_mode] = ratio = statistics.median(ratios)
        print(
            f"{obs_mode:<12}{local:>20.1f}{remote:>18.1f}{ratio:>8.3f}"
            f"  {min(ratios):.3f}-{max(ratios):.3f}"
        )
    print(f"protocol_state_ratio {figures['state_dict']:.3f}")


if __name__ == "__main__":
    main()
