"""The base image participants build on (docker/policy-base/Dockerfile) and the policy template
on top of it, built with Podman exactly as a participant would, scored like the in-process run.

No registry is reachable here, so the Dockerfile's Debian base is replaced (its DEBIAN build
argument) by a bare Debian bookworm made with debootstrap: minbase, no Python, no `policy` user,
what the official slim image is. Everything the Dockerfile does then happens for real.
"""

from __future__ import annotations

import fcntl
import os
import random
import shutil
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from evaluator.evaluation import evaluate
from evaluator.plan import build_plan
from evaluator.results import episode_records
from evaluator.sources import LocalDirectory
from evaluator.suite import load_suite
from tests.deploy.dockerfiles import DOCKER
from tests.evaluator.conftest import SCRIPTED
from tests.server.registry_fixture import (
    LocalRegistry,
    fixture_registry,  # noqa: F401 - pytest fixture
)
from tests.worker.container_fixtures import (  # noqa: F401 - pytest fixtures
    SDK,
    TEMPLATE,
    ContainerEngine,
    fixture_container_engine,
    untag,
)
from worker.containers import POLICY_UID, ContainerImage

STAND_IN = "localhost/manieval-test/debian-minbase:bookworm"
LOCK = Path("/run/lock/manieval-debian-minbase.lock")
MIRROR = os.environ.get("DEBIAN_MIRROR", "http://deb.debian.org/debian")


def debian_stand_in(engine: ContainerEngine) -> str:
    """A bare Debian bookworm image, built once per machine and kept in Podman's store."""
    LOCK.parent.mkdir(parents=True, exist_ok=True)
    with LOCK.open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # sessions running at once share the image store
        exists = subprocess.run(["podman", "image", "exists", STAND_IN], env=engine.env)
        if exists.returncode == 0:
            return STAND_IN
        with tempfile.TemporaryDirectory(dir="/var/tmp") as rootfs:
            built = subprocess.run(
                ["debootstrap", "--variant=minbase", "bookworm", rootfs, MIRROR],
                capture_output=True,
                text=True,
                timeout=900,
            )
            if built.returncode != 0:
                pytest.fail(f"debootstrap failed:\n{built.stdout[-3000:]}")
            tar = subprocess.Popen(
                ["tar", "--numeric-owner", "-C", rootfs, "-c", "."], stdout=subprocess.PIPE
            )
            imported = subprocess.run(
                ["podman", "import", "--quiet", "-", STAND_IN],
                stdin=tar.stdout,
                env=engine.env,
                capture_output=True,
                text=True,
            )
            tar.wait()
            if imported.returncode != 0:
                pytest.fail(f"podman import failed:\n{imported.stderr[-3000:]}")
    return STAND_IN


@pytest.fixture(scope="module")
def session() -> str:
    return uuid.uuid4().hex[:8]


@pytest.fixture(scope="module")
def policy_base(container_engine: ContainerEngine, session: str) -> Iterator[str]:
    """docker/policy-base/Dockerfile built on the stand-in; untagged afterwards (its layers stay
    in Podman's cache for the next session)."""
    tag = f"localhost/manieval-test/policy-base:{session}"
    container_engine.podman(
        "build",
        "--quiet",
        "--build-arg",
        f"DEBIAN={debian_stand_in(container_engine)}",
        "--tag",
        tag,
        str(DOCKER / "policy-base"),
        timeout=900,
    )
    yield tag
    untag(container_engine.env, tag)


def test_the_base_runs_the_sdks_dependencies_as_the_policy_user_without_network(
    container_engine: ContainerEngine, policy_base: str
):
    script = "import os, numpy, msgpack; print(os.getuid(), os.getgid(), numpy.__version__)"
    out = container_engine.podman(
        "run", "--rm", "--network=none", "--read-only", policy_base, "python3", "-c", script
    )
    uid, gid, _numpy = out.split()
    assert (int(uid), int(gid)) == (POLICY_UID, POLICY_UID)


@pytest.mark.sim
def test_the_template_on_the_base_scores_like_the_in_process_run(
    container_engine: ContainerEngine,
    registry: LocalRegistry,
    policy_base: str,
    session: str,
    tmp_path: Path,
):
    # What a participant does: copy the template, put the SDK beside it, write policy.py, build.
    context = tmp_path / "my-policy"
    shutil.copytree(TEMPLATE, context)
    shutil.copytree(SDK, context / "manieval_sdk", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(SCRIPTED / "policy.py", context / "policy.py")
    local = f"localhost/manieval-test/template-on-base:{session}"
    container_engine.podman(
        "build", "--quiet", "--build-arg", f"BASE={policy_base}", "--tag", local, str(context)
    )
    remote = f"{registry.domain}/manieval-test/template-on-base"
    digest_file = tmp_path / "digest"
    container_engine.podman(
        "push",
        "--quiet",
        "--tls-verify=false",
        "--digestfile",
        str(digest_file),
        local,
        f"docker://{remote}:{session}",
    )
    pinned = f"{remote}@{digest_file.read_text().strip()}"
    plan = build_plan(
        load_suite("maniskill-core"),
        "dev",
        tasks=["PickCube-v1", "PushCube-v1"],
        conditions=["nominal"],
        episodes=2,
    )
    source = ContainerImage(
        pinned,
        submission=random.randrange(10**6, 10**9),
        attempt=1,
        engine_url=container_engine.url,
    )
    try:
        in_container = evaluate(plan, source)
    finally:
        untag(container_engine.env, local, pinned)
    in_process = evaluate(plan, LocalDirectory(SCRIPTED))
    assert in_container.status == "completed", in_container.abort
    assert episode_records(in_container) == episode_records(in_process)
    assert in_container.score == in_process.score > 0
