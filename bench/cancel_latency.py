"""Cancel latency per executor: from the participant's cancel, mid-episode, to a stopped run.

- local process: the embedded service (`manieval.service.Service`, SQLite in a temporary data
  directory) runs the bundled `local:scripted` policy; the cancel is the public API's
  `POST /api/v1/submissions/{id}/cancel`; stopped = every process the run added to this
  process's tree (bubblewrap and the policy in it) has exited.
- container: a worker (`worker.run.run_next`, docker executor) against the server in-process
  (tests/workers.py), the scripted policy as an image run by Podman's Docker API; the cancel is
  `server.submissions.service.cancel`, what the API route calls; stopped = the engine reports
  the attempt's container (found by its labels before the cancel) gone or not running.
- Kubernetes: `run_as_job` through `run_next` against the API-server double
  (tests/worker/k8s_double.py), `k8s_poll_interval` at its default; stopped = the Job's DELETE
  reached the double. Separately, the pod's evaluator (`python -m evaluator.job`, a real
  scripted policy connected) mid-episode: from SIGTERM to its exit. The executor's figure is
  the sum of the two medians (the kubelet's own delay between them is not modelled).

Every episode runs to its step limit (`ignore_terminations`); each cancel comes a random 2-4 s
after an episode ended, well inside the next one (the episode's length is printed). Needs root,
podman, runc, bubblewrap, debootstrap (the base image, built once) and lavapipe:

    .venv/bin/python bench/cancel_latency.py [--reps 5] [--steps 900] [--only local,container]
"""

from __future__ import annotations

import argparse
import logging
import operator
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import psutil  # type: ignore[import-untyped]
from docker.errors import NotFound
from docker.models.containers import Container
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload, sessionmaker

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.loopback import free_port  # noqa: E402
from evaluator.job import evaluation_job  # noqa: E402
from evaluator.plan import build_plan  # noqa: E402
from evaluator.suite import load_suite  # noqa: E402
from internal_api.schemas import State  # noqa: E402
from manieval.service import Service  # noqa: E402
from server.challenges.service import ChallengeOptions, load_challenge  # noqa: E402
from server.kit.db import make_engine, session_factory, upgrade  # noqa: E402
from server.kit.settings import Settings  # noqa: E402
from server.models import Challenge, Submission, User  # noqa: E402
from server.registry.published import LOCAL_POLICY_BASE  # noqa: E402
from server.submissions.service import Resolved, cancel, submit  # noqa: E402
from testkit.factories import PASSWORD, make_user  # noqa: E402
from testkit.k8s_double import (  # noqa: E402
    EVALUATOR_IMAGE,
    NAMESPACE,
    POLICY_IMAGE,
    ApiServerDouble,
)
from testkit.workers import server_api, server_app, worker_settings  # noqa: E402
from worker.containers import LABEL_ATTEMPT, LABEL_SUBMISSION, engine  # noqa: E402
from worker.kubernetes.manifest import job_name  # noqa: E402
from worker.run import run_next  # noqa: E402
from worker.server_api import ServerAPI  # noqa: E402

API = "/api/v1"
SCRIPTED = REPO / "examples" / "policies" / "scripted"
BASE_IMAGE = LOCAL_POLICY_BASE
TEMPLATE_IMAGE = "localhost/manieval-bench/cancel-template:latest"
POLICY_TAG = "localhost/manieval-bench/cancel-scripted:latest"
CHALLENGE = "bench-cancel"
SUITE = """\
name: bench-cancel
version: 1
tasks:
  - {{env_id: PickCube-v1, max_episode_steps: {steps}, episodes: 40}}
phases:
  dev: {{seeds: {{kind: public, start: 0}}}}
limits: {{connect_timeout_s: 120, first_call_timeout_s: 120, call_timeout_s: 10, budget_s: 5000}}
ignore_terminations: true
"""
FINAL = ("succeeded", "failed", "error", "cancelled", "timed_out")
POLL_S = 0.005  # looking for the stop; polls of progress are every 0.05 s, light on the GIL


@dataclass
class Figures:
    """Latencies of one measured stop, and how far into its episode each cancel came."""

    name: str
    latencies: list[float] = field(default_factory=list)
    into_episode: list[float] = field(default_factory=list)

    def print(self, episode_s: float | None) -> float:
        median, worst = statistics.median(self.latencies), max(self.latencies)
        runs = " ".join(f"{x:.3f}" for x in self.latencies)
        into = " ".join(f"{x:.1f}" for x in self.into_episode)
        print(f"{self.name}: median {median:.3f} s, max {worst:.3f} s  [{runs}]")
        if episode_s is None:
            print(f"  cancelled {into} s after its pod started")
            return median
        inside = sum(
            a + b < episode_s for a, b in zip(self.into_episode, self.latencies, strict=True)
        )
        print(f"  cancelled {into} s into an episode of ~{episode_s:.1f} s", end="")
        print(f" (cancel and stop within one episode: {inside} of {len(self.latencies)})")
        return median


def until(
    check: Callable[[], object], what: str, timeout: float = 300.0, every: float = 0.02
) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := check()):
        if time.monotonic() > deadline:
            sys.exit(f"gave up waiting for {what}")
        time.sleep(every)
    return value


def bench_settings(data_dir: Path) -> Settings:
    return Settings(
        dev_mode=True,
        data_dir=data_dir,
        cookie_secure=False,
        allow_local_policies=True,
        register_rate="1000/minute",
        login_rate="1000/minute",
        token_rate="1000/minute",
        submit_rate="1000/minute",
    )


def database(settings: Settings, suite: Path) -> sessionmaker[Session]:
    """A migrated SQLite database holding the bench's challenge; its session factory."""
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        options = ChallengeOptions(quota_per_day=1000, quota_concurrent=1)
        load_challenge(db, suite, options, seed_secret=settings.secret("seed_secret"))
    return sessions


class EpisodeClock:
    """Times episode ends from a count that grows by one per episode (polled); keeps the
    lengths of the episodes seen whole, across runs."""

    def __init__(self) -> None:
        self.ends: list[float] = []
        self.lengths: list[float] = []

    def start(self) -> None:
        self.lengths += [b - a for a, b in zip(self.ends, self.ends[1:], strict=False)]
        self.ends = []

    def saw(self, done: int) -> None:
        while len(self.ends) < done:
            self.ends.append(time.monotonic())

    def length(self) -> float | None:
        self.start()
        return statistics.median(self.lengths) if self.lengths else None


# Local process: the embedded service and its public API ----------------------------------


def alive(process: psutil.Process) -> bool:
    try:
        return bool(process.is_running() and process.status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


def descendants() -> dict[int, psutil.Process]:
    return {p.pid: p for p in psutil.Process(os.getpid()).children(recursive=True)}


def bench_local(work: Path, suite: Path, reps: int) -> tuple[Figures, float | None]:
    settings = bench_settings(work / "local")
    service = Service(settings, port=free_port(), sessions=database(settings, suite))
    if not service.start():
        sys.exit("the embedded service did not start")
    figures, clock = Figures("local process (policy process exited)"), EpisodeClock()
    try:
        with httpx.Client(base_url=service.url, timeout=60) as client:
            user = {"username": "bench", "email": "bench@example.org", "password": PASSWORD}
            client.post(f"{API}/users", json=user).raise_for_status()
            login = {"login": "bench", "password": PASSWORD}
            token = client.post(f"{API}/auth/token", json=login).json()["token"]
            client.headers["Authorization"] = f"Bearer {token}"
            for rep in range(reps):
                local_rep(client, figures, clock, warm=rep == 0)
        if service.worker is not None:  # the last stop done: else it claims from a server gone
            service.worker.queue.idle.wait(60)
    finally:
        service.stop()
    return figures, clock.length()


def local_rep(client: httpx.Client, figures: Figures, clock: EpisodeClock, *, warm: bool) -> None:
    before = set(descendants())
    body = {"challenge": CHALLENGE, "image": "local:scripted", "description": "cancel bench"}
    r = client.post(f"{API}/submissions", json=body)
    r.raise_for_status()
    sid = r.json()["id"]
    clock.start()

    def done() -> int:
        got = client.get(f"{API}/submissions/{sid}").json()
        if got["state"] in FINAL:
            sys.exit(f"submission {sid} ended before the cancel: {got['state']}")
        count = int((got.get("progress") or {}).get("done", 0))
        clock.saw(count)
        return count

    until(lambda: done() >= (2 if warm else 1), "episodes to stream", every=0.05)
    delay = random.uniform(2.0, 4.0)
    while time.monotonic() < clock.ends[-1] + delay:
        done()  # an episode ending meanwhile moves the mark: the cancel stays mid-episode
        time.sleep(0.05)
    policy = [p for pid, p in descendants().items() if pid not in before]
    if not policy:
        sys.exit("no policy process found under this process")
    started = time.monotonic()
    client.post(f"{API}/submissions/{sid}/cancel").raise_for_status()
    until(lambda: not any(alive(p) for p in policy), "the policy to exit", every=POLL_S)
    figures.latencies.append(time.monotonic() - started)
    figures.into_episode.append(started - clock.ends[-1])
    until(lambda: client.get(f"{API}/submissions/{sid}").json()["state"] in FINAL, "the end")


# An in-process server, a worker thread, the service's own cancel -------------------------


@dataclass
class Bed:
    """The server in-process with the bench's challenge and one participant."""

    sessions: sessionmaker[Session]
    settings: Settings
    user_id: int

    def submit(self, image: str) -> int:
        with self.sessions.begin() as db:
            user = db.get_one(User, self.user_id)
            query = select(Challenge).options(selectinload(Challenge.phases))
            challenge = db.scalars(query.filter_by(slug=CHALLENGE)).one()
            phase = next(p for p in challenge.phases if p.name == "dev")
            submission = submit(
                db,
                user=user,
                challenge=challenge,
                phase=phase,
                image=image,
                description="cancel bench",
                public=False,
                resolve=lambda _image: Resolved(pinned=image, size_bytes=1),
            )
            db.flush()
            return submission.id

    def submission(self, sid: int) -> Submission:
        with self.sessions() as db:
            return db.get_one(Submission, sid)

    def cancel(self, sid: int) -> None:
        """What `POST /api/v1/submissions/{id}/cancel` does after its auth checks."""
        with self.sessions.begin() as db:
            cancel(db, db.get_one(User, self.user_id), db.get_one(Submission, sid))


def make_bed(data_dir: Path, suite: Path) -> Bed:
    settings = bench_settings(data_dir)
    sessions = database(settings, suite)
    with sessions() as db:
        return Bed(sessions, settings, make_user(db, "bench").id)


@contextmanager
def worker_thread(api: ServerAPI, wsettings: Any) -> Iterator[threading.Thread]:
    """`run_next` as a Celery task runs it, claiming the one queued submission."""
    thread = threading.Thread(target=run_next, args=(api, wsettings), daemon=True)
    thread.start()
    yield thread
    thread.join(timeout=120)
    if thread.is_alive():
        sys.exit("the worker did not end the attempt")


def wait_streaming(bed: Bed, sid: int, clock: EpisodeClock, episodes: int) -> None:
    def done() -> int:
        submission = bed.submission(sid)
        if submission.state.final:
            sys.exit(f"submission {sid} ended before the cancel: {submission.reason}")
        count = int((submission.progress or {}).get("done", 0))
        clock.saw(count)
        return count

    clock.start()
    until(lambda: done() >= episodes, "episodes to stream", every=0.05)
    delay = random.uniform(2.0, 4.0)
    while time.monotonic() < clock.ends[-1] + delay:
        done()
        time.sleep(0.05)


# Container: the docker executor against Podman's Docker API ------------------------------


def podman(env: dict[str, str], *args: str) -> str:
    done = subprocess.run(["podman", *args], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"podman {' '.join(args)} failed:\n{done.stderr[-2000:]}")
    return done.stdout.strip()


def build_policy_image(env: dict[str, str], work: Path) -> str:
    """Base (cached), the template with the SDK, the scripted policy; pinned by digest."""
    subprocess.run([str(REPO / "docker" / "policy-base" / "build.sh")], env=env, check=True)
    context = work / "template"
    shutil.copytree(REPO / "examples" / "policy-template", context)
    sdk = REPO / "evaluator" / "sdk" / "manieval_sdk"
    shutil.copytree(sdk, context / "manieval_sdk", ignore=shutil.ignore_patterns("__pycache__"))
    podman(
        env, "build", "-q", "--build-arg", f"BASE={BASE_IMAGE}", "-t", TEMPLATE_IMAGE, str(context)
    )
    policy = work / "policy"
    policy.mkdir()
    shutil.copy(SCRIPTED / "policy.py", policy / "policy.py")
    dockerfile = f"FROM {TEMPLATE_IMAGE}\nCOPY policy.py /opt/policy/policy.py\n"
    (policy / "Dockerfile").write_text(dockerfile)
    podman(env, "build", "-q", "-t", POLICY_TAG, str(policy))
    digest = podman(env, "image", "inspect", "--format", "{{.Digest}}", POLICY_TAG)
    return f"{POLICY_TAG.rsplit(':', 1)[0]}@{digest}"


@contextmanager
def podman_service(work: Path) -> Iterator[tuple[str, dict[str, str]]]:
    """Podman's Docker API on a socket in `work`, configured as the tests configure it."""
    env = {**os.environ, "CONTAINERS_CONF": str(REPO / "docker" / "containers.conf")}
    url = f"unix://{work / 'podman.sock'}"
    service = subprocess.Popen(
        ["podman", "system", "service", "--time=0", url],
        cwd=work,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        until(lambda: (work / "podman.sock").exists(), "podman's socket", timeout=30)
        with closing(engine(url)):
            pass
        yield url, env
    finally:
        service.terminate()
        service.wait(timeout=30)


def all_stopped(containers: list[Container]) -> bool:
    """Whether the engine says none of `containers` runs (gone counts as stopped). Each is
    inspected by itself: Podman's list locks every container of the store, so another
    session's container in a long stop would stall a listing for seconds."""
    for container in containers:
        try:
            container.reload()
        except NotFound:
            continue
        if container.status == "running":
            return False
    return True


def bench_container(work: Path, suite: Path, reps: int) -> tuple[Figures, float | None]:
    figures, clock = Figures("container (no running container)"), EpisodeClock()
    bed = make_bed(work / "container", suite)
    with podman_service(work) as (url, env):
        image = build_policy_image(env, work)
        wsettings = worker_settings(bed.settings, docker_engine_url=url, policy_memory_mib=1024)
        api = server_api(server_app(bed.settings, bed.sessions), wsettings)
        probe = engine(url)
        try:
            for rep in range(reps):
                sid = bed.submit(image)
                labels = [f"{LABEL_SUBMISSION}={sid}", f"{LABEL_ATTEMPT}=1"]
                with worker_thread(api, wsettings):
                    wait_streaming(bed, sid, clock, 2 if rep == 0 else 1)
                    found = probe.containers.list(filters={"label": labels})  # running ones
                    if not found:
                        sys.exit("the policy container is not running")
                    started = time.monotonic()
                    bed.cancel(sid)
                    until(partial(all_stopped, found), "the container to stop", every=POLL_S)
                    figures.latencies.append(time.monotonic() - started)
                    figures.into_episode.append(started - clock.ends[-1])
        finally:
            probe.close()
            api.close()
            for tag in (POLICY_TAG, TEMPLATE_IMAGE):
                subprocess.run(["podman", "rmi", tag], env=env, capture_output=True)
    return figures, clock.length()


# Kubernetes: the Job's deletion, and the evaluator's exit on SIGTERM ---------------------


@dataclass
class TimedDouble(ApiServerDouble):
    """The API-server double, noting when each Job's DELETE arrived."""

    deleted_at: dict[str, float] = field(default_factory=dict)

    def _delete_job(
        self, namespace: str, name: str, query: dict[str, list[str]], body: Any
    ) -> tuple[int, Any]:
        self.deleted_at.setdefault(name, time.monotonic())
        return super()._delete_job(namespace, name, query, body)


def bench_job_delete(work: Path, suite: Path, reps: int) -> Figures:
    figures = Figures("Kubernetes Job (DELETE reached the API server)")
    bed = make_bed(work / "k8s", suite)
    double = TimedDouble()
    with double:
        wsettings = worker_settings(
            bed.settings,
            executor="kubernetes",
            k8s_api_url=double.host,
            k8s_namespace=NAMESPACE,
            evaluator_image=EVALUATOR_IMAGE,
        )  # k8s_poll_interval: the default
        api = server_api(server_app(bed.settings, bed.sessions), wsettings)
        try:
            for _ in range(reps):
                sid = bed.submit(POLICY_IMAGE)
                name = job_name(sid, 1)
                with worker_thread(api, wsettings):
                    until(partial(operator.contains, double.jobs, (NAMESPACE, name)), "the Job")
                    double.run(NAMESPACE, name)  # the controller and the kubelet start it
                    log = "manieval: run 0 episode 0: success\n"
                    double.write_log(NAMESPACE, name, "evaluator", log)
                    delay = random.uniform(2.0, 4.0)
                    time.sleep(delay)
                    started = time.monotonic()
                    bed.cancel(sid)
                    until(
                        partial(operator.contains, double.deleted_at, name),
                        "the DELETE",
                        every=POLL_S,
                    )
                    figures.latencies.append(double.deleted_at[name] - started)
                    figures.into_episode.append(delay)
                if bed.submission(sid).state != State.CANCELLED:
                    sys.exit(f"the Job of {sid} did not end cancelled")
        finally:
            api.close()
    return figures


def bench_pod_sigterm(suite: Path, reps: int) -> tuple[Figures, float | None]:
    figures, clock = Figures("Kubernetes pod (evaluator exit after SIGTERM)"), EpisodeClock()
    job = evaluation_job(build_plan(load_suite(suite), "dev"), suite_yaml=suite.read_text())
    for rep in range(reps):
        pod_rep(job.canonical_json(), figures, clock, episodes=2 if rep == 0 else 1)
    return figures, clock.length()


def pod_rep(job_spec: str, figures: Figures, clock: EpisodeClock, *, episodes: int) -> None:
    """Be the kubelet: the evaluator and the policy as processes; SIGTERM the evaluator."""
    endpoint = Path(tempfile.mkdtemp(prefix="mev-", dir="/tmp"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")}
    env |= {
        "MANIEVAL_JOB_SPEC": job_spec,
        "MANIEVAL_SHARDS": "1",
        "MANIEVAL_ENDPOINT_DIR": str(endpoint),
    }
    policy = subprocess.Popen(
        [sys.executable, str(SCRIPTED / "policy.py")],
        cwd=SCRIPTED,
        env={"MANIEVAL_ENDPOINT": f"unix://{endpoint}/policy.sock"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    evaluator = subprocess.Popen(
        [sys.executable, "-m", "evaluator.job"],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    clock.start()

    def read() -> None:
        assert evaluator.stderr is not None
        for line in evaluator.stderr:
            if line.startswith("manieval: run "):
                clock.saw(len(clock.ends) + 1)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        until(lambda: len(clock.ends) >= episodes and evaluator.poll() is None, "episodes")
        delay = random.uniform(2.0, 4.0)
        while time.monotonic() < clock.ends[-1] + delay:
            time.sleep(0.01)
        started = time.monotonic()
        evaluator.send_signal(signal.SIGTERM)
        code = evaluator.wait(timeout=60)
        figures.latencies.append(time.monotonic() - started)
        figures.into_episode.append(started - clock.ends[-1])
        if code != 128 + signal.SIGTERM:
            sys.exit(f"the evaluator exited {code}, not by its SIGTERM handler")
    finally:
        for process in (evaluator, policy):
            process.kill()
            process.wait()
        reader.join(timeout=10)
        shutil.rmtree(endpoint, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--steps", type=int, default=900, help="steps per episode")
    parser.add_argument("--only", default="local,container,kubernetes")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    only = set(args.only.split(","))
    medians: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="mev-cancel-", dir="/tmp") as tmp:
        work = Path(tmp)
        suite = work / "bench-cancel.yaml"
        suite.write_text(SUITE.format(steps=args.steps))
        print(f"load average at start: {Path('/proc/loadavg').read_text().strip()}")
        if "local" in only:
            figures, length = bench_local(work, suite, args.reps)
            medians["local"] = figures.print(length)
        if "container" in only:
            figures, length = bench_container(work, suite, args.reps)
            medians["container"] = figures.print(length)
        if "kubernetes" in only:
            delete = bench_job_delete(work, suite, args.reps)
            sigterm, length = bench_pod_sigterm(suite, args.reps)
            total = delete.print(None) + sigterm.print(length)
            worst = max(delete.latencies) + max(sigterm.latencies)
            print(f"Kubernetes, DELETE + SIGTERM exit: median {total:.3f} s, max {worst:.3f} s")
            medians["kubernetes"] = total
        print(f"load average at end: {Path('/proc/loadavg').read_text().strip()}")
    print(f"cancel_latency_max_s {max(medians.values()):.3f}")


if __name__ == "__main__":
    main()
