"""Shards: 2 evaluator workers against 1 on the same 40 PickCube-v1 episodes, on a warm machine.

A worker machine pays its start-up once (`evaluator.pool`: processes that have imported torch and
ManiSkill, kept between evaluations), so what sharding must speed up is an evaluation on warm
processes. This bench warms a pool of 1 and a pool of 2 processes (a first, uncounted round),
then runs the bundled scripted policy's evaluation through each in turn, the order alternating
per round so that a busy machine slows both alike. It prints each round's times and ratio,
checks that every run gives the same records (each episode's seed, success, steps, return and
failure: what must not depend on how the work is split), and ends with the line
`shard_speedup_2_over_1 <ratio>`: the median of the rounds' ratios (the aim is 1.8 on 2 cores).

`--cold` measures instead what a person sees from a fresh `manieval evaluate --workers N`
command, start-up included (ends with `shard_speedup_cold_2_over_1`).

    .venv/bin/python bench/shard_speedup.py [--episodes 40] [--rounds 5] [--cold]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluator.evaluation import evaluate  # noqa: E402
from evaluator.plan import EvaluationPlan, build_plan  # noqa: E402
from evaluator.results import EvaluationResult  # noqa: E402
from evaluator.sources import LocalDirectory  # noqa: E402
from evaluator.suite import load_suite  # noqa: E402

POLICY = REPO / "examples" / "policies" / "scripted"
SUITE = REPO / "suites" / "maniskill-core.yaml"
TASK = "PickCube-v1"
RECORDED = ("index", "seed", "success_once", "success_at_end", "steps", "episode_return")
Records = list[tuple[Any, ...]]


def records(doc: dict[str, Any]) -> Records:
    """What an evaluation decides, per episode, in order: none of it may depend on sharding."""
    return [
        (condition["name"], task["env_id"], *(episode[k] for k in RECORDED), episode["failure"])
        for condition in doc["conditions"]
        for task in condition["tasks"]
        for episode in task["episodes"]
    ]


def warm_run(plan: EvaluationPlan, workers: int) -> tuple[float, Records]:
    """One evaluation on a warm pool of `workers` processes: its wall time and records."""
    started = time.perf_counter()
    result: EvaluationResult = evaluate(plan, LocalDirectory(POLICY), workers=workers, warm=True)
    took = time.perf_counter() - started
    if result.abort is not None:
        sys.exit(f"the evaluation aborted: {result.abort.reason}")
    return took, records(result.model_dump(mode="json"))


def cold_run(workers: int, episodes: int, out: Path) -> tuple[float, Records]:
    """One whole `manieval evaluate` command, as a person runs it: its wall time and records."""
    venv = REPO / ".venv" / "bin" / "manieval"
    argv = [str(venv) if venv.exists() else "manieval", "evaluate", "--policy", str(POLICY)]
    argv += ["--tasks", TASK, "--condition", "nominal", "--episodes", str(episodes)]
    argv += ["--workers", str(workers), "--json", str(out)]
    started = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env={**os.environ}, check=False)
    took = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"{' '.join(argv)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return took, records(json.loads(out.read_text()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--cold", action="store_true", help="whole commands, start-up included")
    args = parser.parse_args()
    plan = build_plan(
        load_suite(SUITE), "dev", tasks=[TASK], conditions=["nominal"], episodes=args.episodes
    )
    work = Path(tempfile.mkdtemp(prefix="manieval-shards-"))
    mode = "cold commands" if args.cold else "warm processes"
    print(f"{args.episodes} {TASK} episodes, scripted policy, {os.cpu_count()} cores, {mode}")

    def measure(workers: int, label: str) -> tuple[float, Records]:
        if args.cold:
            return cold_run(workers, args.episodes, work / f"{label}-w{workers}.json")
        return warm_run(plan, workers)

    expected: Records | None = None
    if not args.cold:
        for workers in (1, 2):  # start-up, paid once per machine: not counted
            took, expected = measure(workers, "warm-up")
            print(f"warm-up, {workers} worker(s): {took:.1f} s (start-up included)")
    print(f"{'round':>6}{'1 worker s':>12}{'2 workers s':>13}{'ratio':>8}")
    ratios, times = [], {1: [], 2: []}  # type: ignore[var-annotated]
    for round_no in range(1, args.rounds + 1):
        order = (1, 2) if round_no % 2 else (2, 1)
        took: dict[int, float] = {}
        for workers in order:
            took[workers], got = measure(workers, f"r{round_no}")
            times[workers].append(took[workers])
            expected = expected if expected is not None else got
            if got != expected:
                sys.exit(f"{workers} worker(s) gave different records in round {round_no}")
        ratios.append(took[1] / took[2])
        print(f"{round_no:>6}{took[1]:>12.2f}{took[2]:>13.2f}{ratios[-1]:>8.2f}")
    one, two = statistics.median(times[1]), statistics.median(times[2])
    print(f"median wall time: 1 worker {one:.2f} s, 2 workers {two:.2f} s")
    print(f"ratios: {min(ratios):.2f} to {max(ratios):.2f}")
    print(f"records identical in every run, 1 and 2 workers: yes ({len(expected or [])} episodes)")
    name = "shard_speedup_cold_2_over_1" if args.cold else "shard_speedup_2_over_1"
    print(f"{name} {statistics.median(ratios):.2f}")


if __name__ == "__main__":
    main()
