"""Leaderboard under load: the public leaderboard endpoint of a seeded Postgres, served by
uvicorn, loaded by wrk from another process.

Seeds a fresh database (dropped at the end) with users, submissions in every state, per-task
results and the leaderboard rows they imply (checked against ``refresh`` on a sample), times the
first (uncached) requests, then runs wrk at fixed concurrency and prints requests, req/s,
latency percentiles, errors and the goal check (p95 <= 50 ms at >= 500 req/s). The last line
is `leaderboard_p95_ms <p95 of the last run>`.

What wrk asks for (`--mix`): `honest` (the default, bench/leaderboard_mix.py) is every page of
both phases at four page sizes as JSON, at two as CSV, and the web page under every kind of
sort, thousands of distinct URLs in a shuffled order, while `--writes-per-s` submissions finish
(each one refreshes a leaderboard row and moves the board on, as a worker's report does);
`rotation` is the former figure: 10 JSON pages in turn, nothing written, all cache hits.

How the server runs (`--server-workers`, default 2): as the product is deployed,
k8s/base/api.yaml's two API replicas, each one `manieval serve` process (one uvicorn worker,
at most one CPU) behind a Service that spreads connections over them: here two server processes
on one port (SO_REUSEPORT), the kernel spreading wrk's connections. Each process keeps its own
snapshots, as each replica does. `--server-workers 1` measures one process alone.

    .venv/bin/python bench/leaderboard_load.py [--users 10000] [--submissions 100000]
        [--duration 20] [--connections 16 ...] [--mix honest|rotation] [--writes-per-s 2]
        [--server-workers 2 [--uvicorn-workers]] [--keep-db]

Needs wrk (Debian package ``wrk``) and the local Postgres (``MANIEVAL_BENCH_POSTGRES``, default
``postgresql+psycopg://postgres@127.0.0.1:5432/postgres``).
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
sys.path.insert(0, str(REPO))

import leaderboard_mix as mix  # noqa: E402
import leaderboard_seed as seeding  # noqa: E402
from fastapi import FastAPI  # noqa: E402
from sqlalchemy import Engine, create_engine, text  # noqa: E402
from sqlalchemy.orm import Session  # noqa: E402

from evaluator.results import SuiteRef  # noqa: E402
from server.app import create_app  # noqa: E402
from server.challenges.service import (  # noqa: E402
    ChallengeOptions,
    get_challenge,
    load_challenge,
    suite_of,
)
from server.kit.db import make_engine, upgrade  # noqa: E402
from server.kit.settings import Settings  # noqa: E402

ADMIN_URL = os.environ.get(
    "MANIEVAL_BENCH_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)
SUITE = REPO / "suites" / "maniskill-core.yaml"
SLUG = "maniskill-core"
GOAL_P95_MS = 50.0
GOAL_RPS = 500.0


class NoWork:
    """The server's queue: nothing is submitted during the benchmark."""

    def enqueue(self, submission_id: int, attempt: int) -> None:
        del submission_id, attempt


def server_app() -> FastAPI:
    """The uvicorn factory of the server process; settings come from MANIEVAL_* variables."""
    return create_app(Settings(), work=NoWork(), background=False)


@dataclass(frozen=True)
class Run:
    connections: int
    requests: int
    seconds: float
    p50_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float
    status_errors: int
    socket_errors: int
    cpu: dict[str, float]  # % of one core over the run
    new_db_connections: int  # sessions that ended during the run: the server's pool churning

    @property
    def rps(self) -> float:
        return self.requests / self.seconds

    @property
    def passed(self) -> bool:
        return self.p95_ms <= GOAL_P95_MS and self.rps >= GOAL_RPS


WRK_SCRIPT = """
local paths = {%s}
local n = 0
request = function()
  n = n + 1
  return wrk.format("GET", paths[(n %% #paths) + 1])
end
done = function(summary, latency, requests)
  local e = summary.errors
  io.write(string.format("BENCH %%.0f %%.0f %%.0f %%.0f %%.0f %%.0f %%.0f %%.0f\\n",
    summary.requests, summary.duration, e.status, e.connect + e.read + e.write + e.timeout,
    latency:percentile(50), latency:percentile(95), latency:percentile(99), latency.max))
end
"""


def leaderboard_paths(pages: int) -> list[str]:
    base = f"/api/v1/challenges/{SLUG}/leaderboard"
    return [
        f"{base}?phase={phase}&page={page}&per_page=50"
        for page in range(1, pages + 1)
        for phase in ("dev", "test")
    ]


@dataclass(frozen=True)
class Target:
    """The served database and the server processes under load."""

    base_url: str
    server_pids: set[int]
    admin: Engine
    database: str
    workdir: Path


def run_wrk(target: Target, paths: list[str], *, connections: int, seconds: float) -> Run:
    script = target.workdir / "load.lua"
    script.write_text(WRK_SCRIPT % ", ".join(f'"{p}"' for p in paths))
    sessions = db_sessions(target.admin, target.database)
    before = _cpu_ticks(target.server_pids), resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = ["wrk", "-t1", f"-c{connections}", f"-d{seconds:.0f}s", "--timeout", "5s"]
    out = subprocess.run(
        [*cmd, "-s", str(script), target.base_url], capture_output=True, text=True, check=True
    ).stdout
    after = _cpu_ticks(target.server_pids), resource.getrusage(resource.RUSAGE_CHILDREN)
    found = re.search(r"^BENCH (.*)$", out, re.MULTILINE)
    if found is None:
        raise RuntimeError(f"wrk printed no result:\n{out}")
    n, duration_us, status, sock, p50, p95, p99, top = (float(v) for v in found[1].split())
    tick = os.sysconf("SC_CLK_TCK") * duration_us / 1e6 / 100  # ticks per % of one core
    cpu = {name: (after[0][name] - before[0][name]) / tick for name in before[0]}
    wrk_s = sum(getattr(after[1], f) - getattr(before[1], f) for f in ("ru_utime", "ru_stime"))
    cpu["wrk"] = wrk_s / (duration_us / 1e6) * 100
    cpu["other"] = cpu.pop("busy") - cpu["server"] - cpu["postgres"] - cpu["wrk"]
    return Run(
        connections=connections,
        requests=int(n),
        seconds=duration_us / 1e6,
        p50_ms=p50 / 1000,
        p95_ms=p95 / 1000,
        p99_ms=p99 / 1000,
        max_ms=top / 1000,
        status_errors=int(status),
        socket_errors=int(sock),
        cpu=cpu,
        new_db_connections=db_sessions(target.admin, target.database) - sessions,
    )


def _cpu_ticks(server_pids: set[int]) -> dict[str, float]:
    """CPU ticks so far of the server's process tree, of Postgres (its live processes and,
    through the postmaster, the backends that have exited) and of the whole machine."""
    cpus = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    busy = sum(float(v) for i, v in enumerate(cpus[:8]) if i not in (3, 4))  # less idle, iowait
    ticks = {"server": 0.0, "postgres": 0.0, "busy": busy}
    procs: dict[int, tuple[str, int, list[str]]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            raw = stat.read_text()
        except OSError:
            continue  # exited meanwhile
        comm = raw[raw.index("(") + 1 : raw.rindex(")")]
        fields = raw[raw.rindex(")") + 2 :].split()
        procs[int(stat.parent.name)] = comm, int(fields[1]), fields
    for pid, (comm, ppid, fields) in procs.items():
        used = float(fields[11]) + float(fields[12])  # utime, stime
        if pid in server_pids or ppid in server_pids:
            ticks["server"] += used
        elif comm == "postgres":
            ticks["postgres"] += used
            if procs.get(ppid, ("",))[0] != "postgres":  # the postmaster: add reaped children
                ticks["postgres"] += float(fields[13]) + float(fields[14])
    return ticks


def db_sessions(admin: Engine, name: str) -> int:
    """Connections ever opened to the database (new ones mean the server's pool churns)."""
    with admin.connect() as conn:
        query = text("SELECT sessions FROM pg_stat_database WHERE datname = :n")
        return int(conn.scalar(query, {"n": name}) or 0)


def create_database() -> tuple[Engine, str, str]:
    admin = create_engine(ADMIN_URL, isolation_level="AUTOCOMMIT")
    name = f"manieval_bench_{uuid.uuid4().hex[:10]}"
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    return admin, name, ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"


def drop_database(admin: Engine, name: str) -> None:
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


def prepare(url: str, users: int, submissions: int, sample: int) -> None:
    """Migrate, load the challenge, seed and check the seeded leaderboard against refresh()."""
    t0 = time.perf_counter()
    upgrade(url)
    engine = make_engine(url)
    with Session(engine) as db, db.begin():
        challenge = load_challenge(db, SUITE, ChallengeOptions(), seed_secret="bench" * 8)
        suite = suite_of(challenge)
        layout = seeding.Layout(
            challenge_id=challenge.id,
            phases={phase.name: phase.id for phase in challenge.phases},
            tasks=[task.env_id for task in suite.tasks],
            conditions=[condition.name for condition in suite.conditions],
        )
    print(f"migrated and loaded {SLUG} in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    took, rows = seeding.seed(engine, layout, users=users, submissions=submissions)
    print(
        f"seeded in {time.perf_counter() - t0:.1f} s ("
        + ", ".join(f"{k} {v:.1f} s" for k, v in took.items())
        + ")"
    )
    print("  rows: " + ", ".join(f"{table} {n:,}" for table, n in rows.items()))
    with engine.connect() as conn:
        for phase, phase_id in layout.phases.items():
            query = text("SELECT count(*) FROM leaderboard_entries WHERE phase_id = :p")
            print(f"  {phase}: {conn.scalar(query, {'p': phase_id}):,} leaderboard rows")
    checked, ms = seeding.verify(engine, sample)
    kinds = ", ".join(f"{n} {kind}" for kind, n in checked.items())
    print(f"refresh() rewrites the seeded rows identically for (phase, user) pairs: {kinds}")
    seconds = ms * users * 2e-3
    print(f"  refresh() takes {ms:.1f} ms; one per (phase, user) would seed in ~{seconds:.0f} s")
    engine.dispose()


@dataclass
class Servers:
    base_url: str
    processes: list[subprocess.Popen[bytes]]

    @property
    def pids(self) -> set[int]:
        return {p.pid for p in self.processes}

    def wait_healthy(self, log: Path) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if any(p.poll() is not None for p in self.processes):
                raise RuntimeError(f"a server exited:\n{log.read_text()}")
            try:
                with urllib.request.urlopen(f"{self.base_url}/healthz", timeout=1):
                    return
            except OSError:
                time.sleep(0.2)
        raise RuntimeError("the server did not answer /healthz within 60 s")

    def stop(self) -> None:
        for p in self.processes:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in self.processes:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def serve(port: int) -> None:
    """One server process on its own SO_REUSEPORT socket. Its protocol must say TCP, or asyncio
    leaves TCP_NODELAY off (Nagle then adds ~40 ms per response; so does `uvicorn --fd`)."""
    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind(("127.0.0.1", port))
    config = uvicorn.Config(server_app, factory=True, access_log=False, log_level="warning")
    uvicorn.Server(config).run(sockets=[sock])


def start_servers(url: str, workers: int, uvicorn_workers: bool, data_dir: Path) -> Servers:
    """`workers` server processes sharing one port through SO_REUSEPORT, so that the kernel
    spreads connections over them; or one `uvicorn --workers`, which hands all of wrk's
    keep-alive connections to whichever worker accepts first."""
    env = {
        **os.environ,
        "MANIEVAL_DEV_MODE": "true",
        "MANIEVAL_DATABASE_URL": url,
        "MANIEVAL_DATA_DIR": str(data_dir),
    }
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    if uvicorn_workers:
        uvicorn = [sys.executable, "-m", "uvicorn", "--factory", "leaderboard_load:server_app"]
        commands = [[*uvicorn, "--port", str(port), "--workers", str(workers), "--no-access-log"]]
    else:
        serve_code = f"import leaderboard_load; leaderboard_load.serve({port})"
        commands = [[sys.executable, "-c", serve_code]] * workers
    log = (data_dir / "server.log").open("wb")
    servers = Servers(f"http://127.0.0.1:{port}", [])
    for command in commands:
        servers.processes.append(
            subprocess.Popen(
                command, cwd=BENCH, env=env, stdout=log, stderr=log, start_new_session=True
            )
        )
    servers.wait_healthy(data_dir / "server.log")
    return servers


def timed_get(url: str) -> tuple[float, int]:
    t0 = time.perf_counter()
    with urllib.request.urlopen(url, timeout=30) as response:
        size = len(response.read())
    return (time.perf_counter() - t0) * 1000, size


def cache_misses(base: str, url: str, bumps: int) -> None:
    """Time the first request per phase, then requests right after a version bump."""
    path = leaderboard_paths(1)
    for p in path:
        ms, size = timed_get(base + p)
        print(f"cold first request {p.split('?')[1]}: {ms:.0f} ms ({size:,} bytes)")
    engine = make_engine(url)
    misses = []
    for _ in range(bumps):
        with engine.begin() as conn:
            conn.execute(text("UPDATE phases SET leaderboard_version = leaderboard_version + 1"))
        misses.append(timed_get(base + path[0])[0])
    warm = statistics.median(timed_get(base + path[0])[0] for _ in range(20))
    print(f"after a version bump (dev, median of {bumps}): {statistics.median(misses):.0f} ms;")
    print(f"cached, one client: {warm:.1f} ms")
    engine.dispose()


def board_shape(url: str) -> tuple[SuiteRef, list[str], list[str]]:
    """The challenge's suite reference, tasks and stress conditions."""
    engine = make_engine(url)
    with Session(engine) as db:
        challenge = get_challenge(db, slug=SLUG)
        suite = suite_of(challenge)
        ref = SuiteRef(name=suite.name, version=suite.version, sha256=challenge.suite_hash)
        shape = ref, [t.env_id for t in suite.tasks], [c.name for c in suite.conditions[1:]]
    engine.dispose()
    return shape


def report(runs: list[Run], args: argparse.Namespace, what: str) -> None:
    how = "uvicorn --workers" if args.uvicorn_workers else "uvicorn processes (SO_REUSEPORT):"
    print(
        f"\nwrk: 1 thread, {args.duration:.0f} s per run after {args.warmup:.0f} s of warm-up, "
        f"{what}; {how} {args.server_workers}"
    )
    head = ("conns", "requests", "req/s", "p50 ms", "p95 ms", "p99 ms", "max ms", "errors")
    print("".join(f"{h:>9}" for h in head) + "  goal  cpu% server/pg/wrk/other  db connects")
    for r in runs:
        cells: list[Any] = [r.connections, r.requests, f"{r.rps:.0f}", f"{r.p50_ms:.1f}"]
        cells += [f"{r.p95_ms:.1f}", f"{r.p99_ms:.1f}", f"{r.max_ms:.1f}"]
        cells += [r.status_errors + r.socket_errors]
        cpu = "/".join(f"{r.cpu[k]:.0f}" for k in ("server", "postgres", "wrk", "other"))
        goal = "PASS" if r.passed else "FAIL"
        print(
            "".join(f"{c:>9}" for c in cells) + f"  {goal}  {cpu:>23}  {r.new_db_connections:>11}"
        )
    print(
        f"goal: p95 <= {GOAL_P95_MS:.0f} ms at >= {GOAL_RPS:.0f} req/s. errors: non-2xx and "
        "socket errors. cpu: % of one core (2 cores = 200); 'other' is everything else on the "
        "machine, which should be near 0 for figures to trust. db connects: connections the "
        "server closed during the run (pool churn)."
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--users", type=int, default=10_000)
    parser.add_argument("--submissions", type=int, default=100_000)
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per measured run")
    parser.add_argument("--warmup", type=float, default=5.0, help="seconds of wrk before each")
    parser.add_argument("--connections", type=int, nargs="+", default=[16])
    parser.add_argument("--mix", choices=("honest", "rotation"), default="honest")
    parser.add_argument("--pages", type=int, default=5, help="pages per phase in the rotation")
    parser.add_argument(
        "--writes-per-s", type=float, default=2.0, help="submissions finishing (honest mix)"
    )
    parser.add_argument(
        "--server-workers",
        type=int,
        default=2,
        help="server processes (2: the API replicas of k8s/base/api.yaml)",
    )
    parser.add_argument(
        "--uvicorn-workers",
        action="store_true",
        help="run them as one `uvicorn --workers N` instead of N processes on SO_REUSEPORT",
    )
    parser.add_argument("--verify-sample", type=int, default=25, help="pairs per kind")
    parser.add_argument("--keep-db", action="store_true", help="keep the database; print its URL")
    args = parser.parse_args()
    if shutil.which("wrk") is None:
        sys.exit("wrk is not installed (apt-get install wrk)")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the cleanup below

    admin, name, url = create_database()
    work = Path(tempfile.mkdtemp(prefix="manieval-bench-"))
    servers: Servers | None = None
    try:
        print(f"database {name}: {args.users:,} users, {args.submissions:,} submissions")
        prepare(url, args.users, args.submissions, args.verify_sample)
        servers = start_servers(url, args.server_workers, args.uvicorn_workers, work)
        cache_misses(servers.base_url, url, bumps=5)
        target = Target(servers.base_url, servers.pids, admin, name, work)
        suite, tasks, stresses = board_shape(url)
        if args.mix == "honest":
            reader = make_engine(url)
            paths = mix.mixed_paths(reader, slug=SLUG, tasks=tasks, stresses=stresses)
            reader.dispose()
            what = (
                f"{len(paths):,} distinct URLs in a shuffled order (JSON, CSV, web pages), "
                f"{args.writes_per_s:g} submissions finishing per second"
            )
        else:
            paths = leaderboard_paths(args.pages)
            what = f"rotating {len(paths)} URLs (dev and test, pages 1-{args.pages}, per_page=50)"
        writes_per_s = args.writes_per_s if args.mix == "honest" else 0.0
        finisher = None
        if writes_per_s > 0:
            finisher = mix.Finisher(
                url, per_second=writes_per_s, suite=suite, tasks=tasks, stresses=stresses
            )
            finisher.start()
        runs = []
        started = time.monotonic()
        try:
            for connections in args.connections:
                run_wrk(target, paths, connections=connections, seconds=args.warmup)
                runs.append(run_wrk(target, paths, connections=connections, seconds=args.duration))
        finally:
            if finisher is not None:
                finisher.stop()
        report(runs, args, what)
        if finisher is not None:
            rate = finisher.finished / (time.monotonic() - started)
            print(f"writes: {finisher.finished} submissions finished ({rate:.1f}/s)")
            for problem in finisher.failed[:5]:
                print(f"  a write failed: {problem}")
        print(f"leaderboard_p95_ms {runs[-1].p95_ms:.1f}")
    finally:
        if servers is not None:
            servers.stop()
        if args.keep_db:
            print(f"kept the database: {url}")
        else:
            drop_database(admin, name)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
