"""Shards: `manieval evaluate --workers 2` against `--workers 1` on the same episodes.

Runs the bundled scripted policy on `--episodes` PickCube-v1 episodes (nominal condition) as a
user runs it, whole command and all (imports, environments, policy processes), alternating
1 and 2 workers so that a busy machine slows both alike. Prints each run's wall time, whether
the two give identical records (every episode's seed, success, steps, return and failure:
what must not depend on how the work is split), and ends with the line
`shard_speedup_2_over_1 <ratio>` (median wall time of 1 worker over that of 2; the aim is 1.8
on 2 cores).

    .venv/bin/python bench/shard_speedup.py [--episodes 40] [--rounds 3]
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
POLICY = REPO / "examples" / "policies" / "scripted"
RECORDED = ("index", "seed", "success_once", "success_at_end", "steps", "episode_return")


def manieval() -> str:
    venv = REPO / ".venv" / "bin" / "manieval"
    return str(venv) if venv.exists() else "manieval"


def run(workers: int, episodes: int, out: Path) -> float:
    """Wall time of one whole `manieval evaluate` command."""
    argv = [manieval(), "evaluate", "--policy", str(POLICY), "--tasks", "PickCube-v1"]
    argv += ["--condition", "nominal", "--episodes", str(episodes), "--workers", str(workers)]
    argv += ["--json", str(out)]
    started = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env={**os.environ}, check=False)
    took = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"{' '.join(argv)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return took


def records(path: Path) -> list[tuple[Any, ...]]:
    """What an evaluation decides, per episode, in order: none of it may depend on sharding."""
    doc = json.loads(path.read_text())
    return [
        (condition["name"], task["env_id"], *(episode[k] for k in RECORDED), episode["failure"])
        for condition in doc["conditions"]
        for task in condition["tasks"]
        for episode in task["episodes"]
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="manieval-shards-"))
    times: dict[int, list[float]] = {1: [], 2: []}
    seen: dict[int, list[tuple[Any, ...]]] = {}
    print(f"{args.episodes} PickCube-v1 episodes, scripted policy, {os.cpu_count()} cores")
    print(f"{'round':>6}{'workers':>9}{'wall s':>9}{'episodes':>10}")
    for round_no in range(1, args.rounds + 1):
        for workers in (1, 2):
            out = work / f"r{round_no}-w{workers}.json"
            took = run(workers, args.episodes, out)
            times[workers].append(took)
            got = records(out)
            if seen.setdefault(workers, got) != got:
                sys.exit(f"{workers} worker(s) gave different records in round {round_no}")
            print(f"{round_no:>6}{workers:>9}{took:>9.1f}{len(got):>10}")
    identical = seen[1] == seen[2]
    one, two = statistics.median(times[1]), statistics.median(times[2])
    print(f"median wall time: 1 worker {one:.1f} s, 2 workers {two:.1f} s")
    print(f"records identical across 1 and 2 workers: {'yes' if identical else 'NO'}")
    if not identical:
        sys.exit(1)
    print(f"shard_speedup_2_over_1 {one / two:.2f}")


if __name__ == "__main__":
    main()
