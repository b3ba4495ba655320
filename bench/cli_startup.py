"""How long `manieval --help` and `manieval status --help` take to answer, as a user runs them.

Each command runs N times as a subprocess with the venv's entry point (`.venv/bin/manieval`,
or `manieval` on the PATH), next to `python -c pass` with the same interpreter: the floor, so
that the figure compares across machines (the ratio). The runs alternate so that a busy
machine slows all of them alike. The last line is `cli_help_median_s <seconds>`, the median of
the two help commands together; the aim is under 0.5 s.

    .venv/bin/python bench/cli_startup.py [-n 10]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 0.5


def entry_point() -> str:
    venv = REPO / ".venv" / "bin" / "manieval"
    if venv.exists():
        return str(venv)
    found = shutil.which("manieval")
    if found is None:
        sys.exit("no manieval entry point: install the project (pip install -e .) first")
    return found


def timed(argv: list[str]) -> float:
    env = {**os.environ, "COLUMNS": "100"}
    started = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, env=env, check=False)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"{' '.join(argv)} exited {done.returncode}:\n{done.stderr.decode()[-2000:]}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=10, help="runs of each command")
    args = parser.parse_args()
    manieval = entry_point()
    commands = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "manieval --help": [manieval, "--help"],
        "manieval status --help": [manieval, "status", "--help"],
    }
    for argv in commands.values():  # warm the file cache and the bytecode
        timed(argv)
    times: dict[str, list[float]] = {name: [] for name in commands}
    for _ in range(args.n):
        for name, argv in commands.items():
            times[name].append(timed(argv))
    floor = statistics.median(times["python -c pass"])
    print(f"{'command':<24} {'median s':>9} {'max s':>7} {'x floor':>8}")
    for name, values in times.items():
        median = statistics.median(values)
        print(f"{name:<24} {median:>9.3f} {max(values):>7.3f} {median / floor:>8.1f}")
    helps = times["manieval --help"] + times["manieval status --help"]
    median = statistics.median(helps)
    verdict = "under" if median < TARGET_S else "OVER"
    print(f"load average {os.getloadavg()[0]:.2f}; {verdict} the {TARGET_S} s aim")
    print(f"cli_help_median_s {median:.3f}")


if __name__ == "__main__":
    main()
