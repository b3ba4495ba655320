"""What keeping trajectories costs: the same plan evaluated with and without a trajectory
directory, alternately (so both see the same load), and the files' size per step.

The scripted policy (examples/policies/scripted) on the core suite's tasks, under the nominal
condition, EPISODES episodes each, one worker, no videos:

    .venv/bin/python bench/trajectory_overhead.py [--episodes 3] [--reps 2]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path

from evaluator.evaluation import evaluate
from evaluator.plan import build_plan
from evaluator.sources import LocalDirectory
from evaluator.suite import load_suite

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--reps", type=int, default=2)
    args = parser.parse_args()
    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    suite = load_suite(REPO / "suites" / "maniskill-core.yaml")
    plan = build_plan(suite, "dev", conditions=["nominal"], episodes=args.episodes, videos=0)
    source = LocalDirectory(REPO / "examples" / "policies" / "scripted")
    evaluate(plan, source)  # imports and first builds, outside the timings
    plain: list[float] = []
    kept: list[float] = []
    size = steps = 0
    for _ in range(args.reps):
        started = time.perf_counter()
        evaluate(plan, source)
        plain.append(time.perf_counter() - started)
        with tempfile.TemporaryDirectory() as directory:
            started = time.perf_counter()
            result = evaluate(plan, source, trajectory_dir=Path(directory))
            kept.append(time.perf_counter() - started)
            size = sum(p.stat().st_size for p in Path(directory).iterdir())
        steps = sum(e.steps for c in result.conditions for t in c.tasks for e in t.episodes)
    print(f"episodes: {plan.episode_count()}, steps: {steps}")
    print(f"without trajectories: median {statistics.median(plain):.2f} s ({plain})")
    print(f"with trajectories:    median {statistics.median(kept):.2f} s ({kept})")
    print(f"ratio: {statistics.median(kept) / statistics.median(plain):.3f}")
    print(f"files: {size} bytes, {size / max(steps, 1):.0f} bytes a step")


if __name__ == "__main__":
    main()
