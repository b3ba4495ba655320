"""Executor overhead: the same suite and seeds, the policy in-process-launched vs in a container.

Runs the scripted policy on PickCube-v1 and PushCube-v1 through `LocalDirectory` (a subprocess)
and through `ContainerImage` (the docker executor, against Podman's Docker API on a temporary
socket), end to end with `evaluate`: starting, evaluating and removing the policy. Prints the
throughput of both, their ratio (goal: at least 0.90), and the container's start time, from
`launch()` to the policy's connection (goal: at most 2 s). Rounds alternate between the two so
that machine noise hits both alike; medians are the figures to read.

Needs root, podman, runc and debootstrap (the base image is built once, see docker/):

    .venv/bin/python bench/executor_overhead.py [--rounds 3] [--episodes 20] [--starts 10]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluator.endpoint import PolicyEndpoint  # noqa: E402
from evaluator.evaluation import evaluate  # noqa: E402
from evaluator.plan import EvaluationPlan, build_plan  # noqa: E402
from evaluator.sources import LocalDirectory, PolicySource  # noqa: E402
from evaluator.suite import load_suite  # noqa: E402
from server.registry.published import LOCAL_POLICY_BASE  # noqa: E402
from worker.containers import ContainerImage  # noqa: E402

SCRIPTED = REPO / "examples" / "policies" / "scripted"
BASE_IMAGE = LOCAL_POLICY_BASE
IMAGE = "localhost/manieval-bench/scripted:latest"
TASKS = ["PickCube-v1", "PushCube-v1"]


def podman(*args: str, env: dict[str, str]) -> str:
    done = subprocess.run(["podman", *args], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"podman {' '.join(args)} failed:\n{done.stderr[-2000:]}")
    return done.stdout.strip()


def build_image(env: dict[str, str], work: Path) -> str:
    """Base (cached), template with the SDK, scripted policy on top; its digest reference."""
    subprocess.run([str(REPO / "docker" / "policy-base" / "build.sh")], env=env, check=True)
    context = work / "image"
    shutil.copytree(REPO / "examples" / "policy-template", context)
    shutil.copytree(
        REPO / "evaluator" / "sdk" / "manieval_sdk",
        context / "manieval_sdk",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    shutil.copy(SCRIPTED / "policy.py", context / "policy.py")
    podman(
        "build", "--quiet", "--build-arg", f"BASE={BASE_IMAGE}", "-t", IMAGE, str(context), env=env
    )
    digest = podman("image", "inspect", "--format", "{{.Digest}}", IMAGE, env=env)
    return f"{IMAGE.rsplit(':', 1)[0]}@{digest}"


@contextmanager
def podman_service(env: dict[str, str], work: Path) -> Iterator[str]:
    """Podman's Docker API on a socket in `work`; yields its URL."""
    url = f"unix://{work / 'podman.sock'}"
    service = subprocess.Popen(
        ["podman", "system", "service", "--time=0", url],
        cwd=work,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 20
        while not (work / "podman.sock").exists():
            if time.monotonic() > deadline or service.poll() is not None:
                sys.exit("podman system service did not start")
            time.sleep(0.05)
        yield url
    finally:
        service.terminate()
        service.wait(timeout=10)


def bench_plan(episodes: int) -> EvaluationPlan:
    suite = load_suite("maniskill-core")
    return build_plan(suite, "dev", tasks=TASKS, conditions=["nominal"], episodes=episodes)


def rates(plan: EvaluationPlan, source: PolicySource) -> tuple[float, float]:
    """Steps/s over the whole evaluation (the policy's start and stop included), and over the
    episodes alone (what the executor costs per step)."""
    started = time.monotonic()
    result = evaluate(plan, source)
    elapsed = time.monotonic() - started
    assert result.status == "completed", result.abort
    episodes = [e for c in result.conditions for t in c.tasks for e in t.episodes]
    steps = sum(e.steps for e in episodes)
    return steps / elapsed, steps / sum(e.wall_time_s for e in episodes)


def start_time(source: PolicySource) -> float:
    """Seconds from launch() to the policy's connection."""
    endpoint = PolicyEndpoint()
    started = time.monotonic()
    process = source.launch(endpoint=endpoint.address, socket_dir=endpoint.socket_dir)
    try:
        endpoint.accept(timeout=60, alive=process.alive)
        return time.monotonic() - started
    finally:
        endpoint.close()
        process.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=20, help="per task")
    parser.add_argument("--starts", type=int, default=10, help="container starts to time")
    args = parser.parse_args()
    if os.geteuid() != 0 or shutil.which("podman") is None:
        sys.exit("needs root and podman (apt-get install -y podman runc debootstrap)")
    env = {**os.environ, "CONTAINERS_CONF": str(REPO / "docker" / "containers.conf")}
    with tempfile.TemporaryDirectory(prefix="manieval-bench-") as tmp:
        work = Path(tmp)
        image = build_image(env, work)
        with podman_service(env, work) as url:
            container = ContainerImage(image, submission=0, attempt=0, engine_url=url)
            container.pull()  # as the worker does: the API version and image are at hand
            local = LocalDirectory(SCRIPTED)
            plan = bench_plan(args.episodes)
            rates(plan, local)  # warm-up: imports, first environments
            local_rates, container_rates = [], []
            for _ in range(args.rounds):
                local_rates.append(rates(plan, local))
                container_rates.append(rates(plan, container))
            starts = [start_time(container) for _ in range(args.starts)]
            local_starts = [start_time(local) for _ in range(args.starts)]
    print(f"suite: {', '.join(TASKS)}, {args.episodes} episodes each, {args.rounds} rounds")
    for label, index in (("end to end", 0), ("in episodes", 1)):
        local_rate = statistics.median(r[index] for r in local_rates)
        container_rate = statistics.median(r[index] for r in container_rates)
        print(
            f"{label:>11}: local directory {local_rate:6.1f} steps/s, container "
            f"{container_rate:6.1f} steps/s, ratio {container_rate / local_rate:.3f} (goal >= 0.90)"
        )
    print(
        f"container start, launch() to connection: median {statistics.median(starts):.2f} s, "
        f"max {max(starts):.2f} s over {len(starts)} (goal <= 2 s); "
        f"local subprocess: median {statistics.median(local_starts):.2f} s"
    )


if __name__ == "__main__":
    main()
