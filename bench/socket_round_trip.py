"""The floor under any policy protocol on this machine: a bare round trip over a Unix socket.

One process does busy work of about one simulator step's length (3 ms), then sends a
200-byte message to another process, which answers 40 bytes at once; the figure is the
median time from sending to the answer. No encoding, no checks: what is left is the kernel's
and the scheduler's cost of waking another process on another CPU and being woken back.
`bench/protocol_overhead.py` prints it beside its per-step overhead.

    .venv/bin/python bench/socket_round_trip.py [--trips 2000] [--work-ms 3]
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import time


def answer(sock: socket.socket) -> None:
    """The other end: answer every message at once, until the socket closes."""
    while message := sock.recv(65536):
        sock.sendall(message[:40])


def round_trips(trips: int, work_s: float) -> list[float]:
    """Seconds of each round trip (after a warm-up), with `work_s` of busy work before each."""
    ours, theirs = socket.socketpair()
    pid = os.fork()  # this script imports nothing that starts threads: fork is safe here
    if pid == 0:
        ours.close()
        try:
            answer(theirs)
        finally:
            os._exit(0)
    theirs.close()
    times = []
    message = b"x" * 200
    try:
        for _ in range(trips + 100):
            until = time.perf_counter() + work_s
            while time.perf_counter() < until:
                pass
            sent = time.perf_counter()
            ours.sendall(message)
            ours.recv(65536)
            times.append(time.perf_counter() - sent)
    finally:
        ours.close()
        os.waitpid(pid, 0)
    return times[100:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trips", type=int, default=2000)
    parser.add_argument("--work-ms", type=float, default=3.0)
    args = parser.parse_args()
    times = round_trips(args.trips, args.work_ms / 1000)
    quartiles = statistics.quantiles(times, n=4)
    print(
        f"round trip over a Unix socket after {args.work_ms:g} ms of work, {args.trips} trips: "
        f"median {statistics.median(times) * 1e6:.1f} us "
        f"(quartiles {quartiles[0] * 1e6:.1f}-{quartiles[2] * 1e6:.1f} us)"
    )
    print(f"socket_round_trip_us {statistics.median(times) * 1e6:.1f}")


if __name__ == "__main__":
    main()
