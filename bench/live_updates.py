"""Live updates: 1,000 open submission streams on one server process, pushed vs polled.

One uvicorn server (SQLite, as the embedded default; `--postgres URL` for Postgres) holds
`--streams` server-sent event streams open, spread over `--submissions` running submissions.
The bench then reports progress to random submissions, one change every `--every` seconds,
each carrying the time it was committed, and records when each stream receives it. It runs
twice, side by side on the same server: with changes pushed (`server/submissions/changes.py`,
the default) and with the former behaviour, every stream reading the database once a second
(`fallback_s=1`, signals ignored). It also counts the database reads the streams make while
nothing changes, and the CPU the server takes meanwhile (every thread of this process but the
clients' own). Figures: the delay from a commit to its arrival (median, 95th percentile,
max), reads per stream per minute and server CPU when idle, for both; the last line is the
ratio of the median delays (polled / pushed).

    .venv/bin/python bench/live_updates.py [--streams 1000] [--submissions 100] [--changes 100]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402
import uvicorn  # noqa: E402
from sqlalchemy.orm import Session, sessionmaker  # noqa: E402

from bench.loopback import free_port  # noqa: E402
from server.app import create_app  # noqa: E402
from server.kit.db import make_engine, session_factory, upgrade  # noqa: E402
from server.kit.settings import Settings  # noqa: E402
from server.models import State  # noqa: E402
from server.submissions import events  # noqa: E402
from server.submissions.changes import ChangeFeed  # noqa: E402
from server.submissions.reports import report_progress, report_state  # noqa: E402
from testkit.factories import make_challenge, make_user, queue_submission  # noqa: E402


class Deaf(ChangeFeed):
    """The former behaviour: no signal ever arrives, so streams read on their timer."""

    @contextmanager
    def watch(self, submission_id: int) -> Iterator[asyncio.Event]:
        yield asyncio.Event()


@dataclass
class Counts:
    reads: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


def counting_reads(counts: Counts) -> None:
    """Count every database read a stream makes (`events._poll`)."""
    original = events._poll

    def counted(*args: Any) -> Any:
        with counts.lock:
            counts.reads += 1
        return original(*args)

    events._poll = counted  # type: ignore[assignment]


@contextmanager
def serving(app: Any) -> Iterator[str]:
    port = free_port()
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", backlog=4096)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)


def seeded(settings: Settings, n: int) -> tuple[sessionmaker[Session], list[int]]:
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions() as db:
        challenge = make_challenge(db, quota_concurrent=n, quota_per_day=n)
        ids = []
        for i in range(n):
            s = queue_submission(db, make_user(db, f"user{i:04d}"), challenge)
            s.public = True
            ids.append(s.id)
        db.commit()
        for sid in ids:
            report_state(db, sid, 1, State.LAUNCHING, "starting")
            report_state(db, sid, 1, State.RUNNING, "evaluating")
        db.commit()
    return sessions, ids


@dataclass
class Window:
    since: float = float("inf")  # changes committed from then on are measured


async def listen(
    client: httpx.AsyncClient,
    url: str,
    opened: asyncio.Event,
    arrivals: list[float],
    window: Window,
) -> None:
    """One stream: the delay of every progress event committed within the window."""
    async with client.stream("GET", url) as response:
        opened.set()
        async for line in response.aiter_lines():
            if line.startswith("data: ") and '"sent"' in line:
                sent = json.loads(line[6:]).get("sent")
                if isinstance(sent, float) and sent >= window.since:
                    arrivals.append(time.time() - sent)


async def run_mode(
    base: str,
    sessions: sessionmaker[Session],
    ids: list[int],
    *,
    streams: int,
    changes: int,
    every: float,
    idle_s: float,
    counts: Counts,
) -> dict[str, float]:
    limits = httpx.Limits(max_connections=streams + 10, max_keepalive_connections=0)
    timeout = httpx.Timeout(None, connect=60.0)
    arrivals: list[float] = []
    window = Window()
    with counts.lock:
        counts.reads = 0
    async with httpx.AsyncClient(limits=limits, timeout=timeout) as client:
        opened = [asyncio.Event() for _ in range(streams)]
        tasks = [
            asyncio.create_task(
                listen(
                    client, f"{base}/submissions/{ids[i % len(ids)]}/events", o, arrivals, window
                )
            )
            for i, o in enumerate(opened)
        ]
        await asyncio.gather(*(o.wait() for o in opened))
        while counts.reads < streams:  # every stream past its first read (slow on a busy box)
            await asyncio.sleep(0.2)
        await asyncio.sleep(1.0)
        with counts.lock:
            counts.reads = 0
        # The server's CPU: the whole process's less this thread's (the clients' event loop).
        cpu_before = time.process_time() - time.thread_time()
        await asyncio.sleep(idle_s)
        server_cpu_s = time.process_time() - time.thread_time() - cpu_before
        with counts.lock:
            idle_reads = counts.reads
        window.since = time.time()
        expected = 0
        for k in range(changes):
            sid = random.choice(ids)
            expected += sum(1 for i in range(streams) if ids[i % len(ids)] == sid)
            with sessions.begin() as db:
                report_progress(db, sid, 1, {"done": k + 1, "total": changes, "sent": time.time()})
            await asyncio.sleep(every)
        await asyncio.sleep(3.0)  # the last ones arrive
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    ordered = sorted(arrivals)
    return {
        "arrived": len(arrivals) / expected,
        "median_s": statistics.median(ordered),
        "p95_s": ordered[int(0.95 * (len(ordered) - 1))],
        "max_s": ordered[-1],
        "idle_reads_per_stream_per_min": idle_reads / streams / idle_s * 60,
        "idle_server_cpu": server_cpu_s / idle_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--streams", type=int, default=1000)
    parser.add_argument("--submissions", type=int, default=100)
    parser.add_argument("--changes", type=int, default=100)
    parser.add_argument("--every", type=float, default=0.1, help="seconds between changes")
    parser.add_argument("--idle", type=float, default=10.0, help="seconds of counting idle reads")
    parser.add_argument("--postgres", help="a database URL instead of a temporary SQLite file")
    args = parser.parse_args()
    random.seed(7)
    data = Path(tempfile.mkdtemp(prefix="manieval-live-"))
    database = {"database_url": args.postgres} if args.postgres else {}
    settings = Settings(
        dev_mode=True, data_dir=data, cookie_secure=False, log_level="WARNING", **database
    )
    sessions, ids = seeded(settings, args.submissions)
    counts = Counts()
    counting_reads(counts)
    app = create_app(settings, sessions=sessions, background=False)
    app.state.event_slots = events.StreamSlots(total=args.streams + 10, per_client=args.streams)
    results = {}
    with serving(app) as base:
        for mode in ("pushed", "polled"):
            if mode == "polled":
                app.state.change_feed = Deaf()
                app.state.event_timing = events.StreamTiming(fallback_s=1.0, max_s=3600)
            else:
                app.state.event_timing = events.StreamTiming(max_s=3600)
            print(f"{mode}: {args.streams} streams over {args.submissions} submissions ...")
            results[mode] = asyncio.run(
                run_mode(
                    base,
                    sessions,
                    ids,
                    streams=args.streams,
                    changes=args.changes,
                    every=args.every,
                    idle_s=args.idle,
                    counts=counts,
                )
            )
            r = results[mode]
            print(
                f"  delay median {r['median_s'] * 1000:.0f} ms, p95 {r['p95_s'] * 1000:.0f} ms, "
                f"max {r['max_s'] * 1000:.0f} ms; {r['arrived']:.0%} of the expected events; "
                f"idle: {r['idle_reads_per_stream_per_min']:.1f} reads per stream per minute, "
                f"server CPU {r['idle_server_cpu']:.1%} of a core"
            )
    ratio = results["polled"]["median_s"] / results["pushed"]["median_s"]
    print(f"live_update_delay_polled_over_pushed {ratio:.2f}")


if __name__ == "__main__":
    main()
