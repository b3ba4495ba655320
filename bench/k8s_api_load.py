"""Kubernetes API load of the executor: requests per running Job per minute, 500 Jobs at once.

Runs `worker.kubernetes.watch.run_as_job` for `--jobs` attempts at once (claimed `--ramp` a
second), one thread each as a Celery threads pool would, against the API-server double
(testkit/k8s_double.py), which counts every request by verb and resource. The double
plays the cluster: the Job controller starts each Job's pod as it is created, the evaluator
prints an episode line every `--episode-s` seconds, and after the measured window every Job
succeeds with a result document (read from its log, as in production). The cluster's clock
keeps pace with the wall clock, so that watches get their bookmarks once a minute, as from a
real API server's watch cache. The ManiEval server is
an in-process stand-in: its heartbeats and cancel checks are no Kubernetes requests. The
worker's settings are its defaults (`k8s_poll_interval` 5 s, `k8s_progress_interval` 120 s).

Printed: the requests made while every Job runs (from the moment all are created and followed
to `--window` seconds later), by kind, per Job per minute; what starting and ending one Job
costs (once per Job, not per minute); then `k8s_api_requests_per_job_per_min <value>`, the
requests of the window per running Job per minute (goal: at most 1).

    .venv/bin/python bench/k8s_api_load.py [--jobs 500] [--window 240] [--episode-s 15] [--ramp 10]
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections import Counter
from datetime import UTC, datetime
from io import StringIO
from pathlib import Path
from typing import Any, cast

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluator.evaluation import build_result  # noqa: E402
from evaluator.job import write_document  # noqa: E402
from evaluator.plan import EvaluationPlan, build_plan  # noqa: E402
from evaluator.runner import ShardOutcome  # noqa: E402
from evaluator.suite import load_suite  # noqa: E402
from internal_api.schemas import Assignment, FinalReport, ReportOut, State  # noqa: E402
from testkit.k8s_double import (  # noqa: E402
    EVALUATOR_IMAGE,
    NAMESPACE,
    POLICY_IMAGE,
    ApiServerDouble,
)
from worker.kubernetes.manifest import job_name  # noqa: E402
from worker.kubernetes.watch import run_as_job  # noqa: E402
from worker.server_api import ServerAPI  # noqa: E402
from worker.settings import WorkerSettings  # noqa: E402

# The plan only sizes the documents the stand-in server keeps: two episodes of one task.
SUITE = REPO / "suites" / "maniskill-core.yaml"
FIGURE = "k8s_api_requests_per_job_per_min"


class StandInServer:
    """The ManiEval server's side of `ServerAPI`, in memory: every attempt runs on."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.progress_of: dict[int, dict[str, Any]] = {}
        self.finals: dict[int, State] = {}

    def running(self, submission_id: int, attempt: int, **_: Any) -> ReportOut:
        return ReportOut(applied=True, state=State.RUNNING)

    def progress(self, submission_id: int, attempt: int, progress: Any) -> ReportOut:
        if progress is not None:
            with self.lock:
                self.progress_of[submission_id] = dict(progress)
        return ReportOut(applied=True, state=State.RUNNING)

    def final(self, submission_id: int, attempt: int, report: FinalReport) -> State:
        with self.lock:
            self.finals[submission_id] = report.state
        return report.state

    def following(self) -> int:
        """How many attempts have reported their Job running."""
        with self.lock:
            return sum(1 for p in self.progress_of.values() if p.get("phase") == "running")


def result_document(plan: EvaluationPlan) -> str:
    out = StringIO()
    started = datetime(2026, 5, 1, tzinfo=UTC)
    write_document(build_result(plan, "image", [ShardOutcome()], started=started), out)
    return out.getvalue()


def until(check: Any, what: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            sys.exit(f"gave up waiting for {what}")
        time.sleep(0.2)


def per_minute(counts: Counter[str], jobs: int, seconds: float) -> dict[str, float]:
    return {kind: n / jobs / (seconds / 60) for kind, n in counts.items()}


def keep_cluster_time(double: ApiServerDouble, done: threading.Event) -> None:
    """Move the double's clock (which moves only when told) with the wall clock, until `done`:
    its watches' bookmarks then come once a minute, as a real API server sends them."""
    last = time.monotonic()
    while not done.wait(1.0):
        now = time.monotonic()
        double.advance(now - last)
        last = now


def run(args: argparse.Namespace) -> None:
    plan = build_plan(
        load_suite(SUITE),
        "dev",
        tasks=["PickCube-v1"],
        conditions=["nominal"],
        episodes=2,
        secret=b"k8s-api-load-bench-secret-32-byt",
    )
    document = result_document(plan)
    settings = WorkerSettings(
        worker_token="k8s-api-load-bench-" + "x" * 32,  # type: ignore[arg-type]
        executor="kubernetes",
        evaluator_image=EVALUATOR_IMAGE,
        k8s_namespace=NAMESPACE,
        data_dir=Path("/tmp/manieval-k8s-api-load"),
    )
    server = StandInServer()
    stop = threading.Event()
    # The double publishes every change its methods make at once; no direct edits to scan for.
    with ApiServerDouble(scan_every=5.0) as double:  # bookmarks: once a minute, the default
        double.on_create = lambda namespace, name: double.run(namespace, name)
        ticking = threading.Event()
        threading.Thread(target=keep_cluster_time, args=(double, ticking), daemon=True).start()
        settings = settings.model_copy(update={"k8s_api_url": double.host})
        followers = []
        started = time.monotonic()
        for sid in range(1, args.jobs + 1):
            handed = Assignment(
                submission_id=sid,
                attempt=1,
                image=POLICY_IMAGE,
                plan=plan,
                suite_yaml=SUITE.read_text(),
                shards=1,
            )
            api = cast(ServerAPI, server)
            thread = threading.Thread(
                target=run_as_job, args=(api, settings, handed), kwargs={"stop": stop}, daemon=True
            )
            thread.start()
            followers.append(thread)
            time.sleep(max(0.0, started + sid / args.ramp - time.monotonic()))
        until(lambda: server.following() == args.jobs, "every Job created and followed", 600)
        ramp = time.monotonic() - started
        start_counts = double.counts()
        before = len(double.requests)
        print(f"{args.jobs} Jobs created and followed in {ramp:.1f} s; measuring {args.window} s")

        t0 = time.monotonic()
        episode = 0
        while time.monotonic() - t0 < args.window:  # the evaluators print their episodes
            time.sleep(max(0.0, t0 + (episode + 1) * args.episode_s - time.monotonic()))
            episode += 1
            line = "".join(f"manieval: run 0 episode {i}: success\n" for i in range(episode))
            with double.lock:
                for sid in range(1, args.jobs + 1):
                    double.write_log(NAMESPACE, job_name(sid, 1), "evaluator", line)
        window = time.monotonic() - t0
        during = double.counts(before)
        after = len(double.requests)
        done = sum(1 for p in server.progress_of.values() if p.get("done"))

        for sid in range(1, args.jobs + 1):
            double.succeed(NAMESPACE, job_name(sid, 1), [document])
        for thread in followers:
            thread.join(timeout=600)
        ending = double.counts(after)
        stop.set()
        ticking.set()

    states = Counter(s.value for s in server.finals.values())
    report(args, window, start_counts, during, ending, states, done)


def report(
    args: argparse.Namespace,
    window: float,
    start_counts: Counter[str],
    during: Counter[str],
    ending: Counter[str],
    states: Counter[str],
    done: int,
) -> None:
    jobs = args.jobs
    rates = per_minute(during, jobs, window)
    print(f"\nwhile {jobs} Jobs run ({window:.0f} s): requests by kind")
    print(f"{'request':<24}{'count':>8}{'per Job per min':>18}")
    for kind in sorted(during):
        print(f"{kind:<24}{during[kind]:>8}{rates[kind]:>18.3f}")
    total = sum(during.values())
    figure = total / jobs / (window / 60)
    print(f"{'all':<24}{total:>8}{figure:>18.3f}")
    print(f"\nonce per Job, to start it: {sum(start_counts.values()) / jobs:.2f} requests", end="")
    print(f" ({', '.join(f'{k} {n}' for k, n in sorted(start_counts.items()))})")
    print(f"once per Job, to end it: {sum(ending.values()) / jobs:.2f} requests", end="")
    print(f" ({', '.join(f'{k} {n}' for k, n in sorted(ending.items()))})")
    print(f"progress read from the logs during the window: {done} of {jobs} attempts")
    print(f"final states: {dict(states)}")
    print(
        f"goal: at most 1 request per running Job per minute: {'met' if figure <= 1 else 'NOT met'}"
    )
    print(f"{FIGURE} {figure:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=500)
    parser.add_argument("--window", type=float, default=240.0, help="seconds measured")
    parser.add_argument("--episode-s", type=float, default=15.0, help="seconds per episode")
    parser.add_argument("--ramp", type=float, default=10.0, help="attempts claimed per second")
    args = parser.parse_args()
    if args.jobs < 1 or min(args.window, args.episode_s, args.ramp) <= 0:
        parser.error("--jobs, --window, --episode-s and --ramp must be positive")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    run(args)


if __name__ == "__main__":
    main()
