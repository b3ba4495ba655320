"""`make demo`'s wait: from the command's start to its printed leaderboard, with fresh data.

The install is done (`make demo` checks it first and then only runs `manieval demo`), so this
times what a person waits for after it: `manieval demo --exit-when-done` on an empty
`MANIEVAL_DATA_DIR` and a free loopback port, from the process's start until it has printed the
leaderboard and ended. Each round runs the command's default settings, then, side by side in the
same round, the same command with `--episodes 3` (the demo's count before the 90 s goal), so that
a busy machine slows both alike; the order alternates per round. It prints each round's times
and ends with the line `demo_first_leaderboard_s <seconds>`: the median of the default's rounds
(the aim is 90 s on 2 cores).

    .venv/bin/python bench/demo_time.py [--rounds 3] [--compare-episodes 3]
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.loopback import free_port  # noqa: E402

MANIEVAL = REPO / ".venv" / "bin" / "manieval"
TIMEOUT_S = 1800.0  # a demo that has not ended by then is reported as failed, not waited for


def end_group(process: subprocess.Popen[str]) -> None:
    """End the demo's process group if it still runs: asked first (it stops as on Ctrl-C),
    then killed if it has not ended within 30 s."""
    if process.poll() is not None:
        return
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.communicate(timeout=30)
            return
        except subprocess.TimeoutExpired:
            continue


def demo_once(extra: list[str]) -> float:
    """Seconds from starting `manieval demo --exit-when-done` (fresh data) to its end."""
    with tempfile.TemporaryDirectory(prefix="manieval-demo-bench-") as data:
        env = {**os.environ, "MANIEVAL_DATA_DIR": data}
        command = [str(MANIEVAL), "demo", "--exit-when-done", "--port", str(free_port()), *extra]
        started = time.perf_counter()
        process = subprocess.Popen(
            command,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,  # its own process group: ended whole if it overruns
        )
        try:
            output, _ = process.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise SystemExit(f"{' '.join(command)} did not end within {TIMEOUT_S:.0f} s") from None
        finally:  # overran, or the bench was interrupted: its group ends before its data goes
            end_group(process)
        elapsed = time.perf_counter() - started
        if process.returncode != 0 or "leaderboard" not in output:
            tail = "\n".join(output.splitlines()[-20:])
            raise SystemExit(f"{' '.join(command)} failed ({process.returncode}):\n{tail}")
        return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--compare-episodes", type=int, default=3, help="the other run's --episodes (0: none)"
    )
    args = parser.parse_args()
    if not MANIEVAL.exists():
        raise SystemExit(f"{MANIEVAL} is missing: run `make install` first")
    variants: dict[str, list[str]] = {"default": []}
    if args.compare_episodes:
        variants[f"--episodes {args.compare_episodes}"] = ["--episodes", str(args.compare_episodes)]
    times: dict[str, list[float]] = {name: [] for name in variants}
    print(f"manieval demo --exit-when-done, fresh data directory, {os.cpu_count()} CPUs")
    print(f"{'round':>5}  " + "  ".join(f"{name:>14}" for name in variants))
    for round_ in range(args.rounds):
        order = list(variants) if round_ % 2 == 0 else list(reversed(variants))
        for name in order:
            times[name].append(demo_once(variants[name]))
        print(f"{round_ + 1:>5}  " + "  ".join(f"{times[n][-1]:>13.1f}s" for n in variants))
    for name, values in times.items():
        spread = f"{min(values):.1f}-{max(values):.1f}"
        print(f"{name}: median {statistics.median(values):.1f} s, range {spread} s")
    print(f"demo_first_leaderboard_s {statistics.median(times['default']):.1f}")


if __name__ == "__main__":
    main()
