"""Real policy containers for tests: Podman's Docker API, the base image, images in a registry.

``container_engine`` starts Podman's Docker-API service on a temporary socket for the session,
configured by ``docker/containers.conf`` (through CONTAINERS_CONF, so nothing global is needed)
and trusting the session's plain-HTTP ``registry``. ``policy_images`` builds
``docker/policy-base`` once per machine (Podman's image store keeps it), the policy template on
top with the SDK copied in, and publishes policies as images pushed to the registry and named
by digest.

Sessions at once (pytest's workers, a developer's run beside CI's) share one image store, and
the build cache gives equal builds one image under several sessions' names. So a session only
ever adds names of its own (a session tag) and takes away exactly those (`untag`): it never
re-tags a shared name, and never removes an image by ID or by a digest reference, which Podman
resolves to any image with that digest and deletes when it holds one name, another session's.
A test module imports
the fixtures by their function names::

    from tests.server.registry_fixture import fixture_registry  # noqa: F401 - pytest fixture
    from tests.worker.container_fixtures import (  # noqa: F401 - pytest fixtures
        fixture_container_engine,
        fixture_policy_images,
    )
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
import uuid
from collections.abc import Iterator, Mapping
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from docker.client import DockerClient
from docker.errors import DockerException
from docker.models.containers import Container

from server.registry.published import LOCAL_POLICY_BASE
from tests.server.registry_fixture import LocalRegistry
from worker.containers import LABEL_ATTEMPT, LABEL_ROLE, LABEL_SUBMISSION, ROLE_POLICY, engine

REPO = Path(__file__).resolve().parents[2]
CONTAINERS_CONF = REPO / "docker" / "containers.conf"
BASE_BUILD = REPO / "docker" / "policy-base" / "build.sh"
BASE_IMAGE = LOCAL_POLICY_BASE
TEMPLATE = REPO / "examples" / "policy-template"
SDK = REPO / "evaluator" / "sdk" / "manieval_sdk"
INSTALL_HINT = "apt-get install -y podman runc debootstrap"
_STARTUP_SECONDS = 20.0


def untag(env: Mapping[str, str], *names: str) -> None:
    """Take these names out of the image store and nothing else: `podman untag NAME NAME` never
    deletes an image (what no name holds any more stays as the build cache). Never `rmi` a
    name: `rmi REPO@DIGEST` finds any image with that digest, whatever its names, and deletes
    it where the name it was asked for is not there and one other name is left."""
    for name in names:
        # A name not in the store (never pulled, already gone) is not an error here.
        subprocess.run(
            ["podman", "untag", name, name], env=dict(env), capture_output=True, timeout=60
        )


def session_tag() -> str:
    """A tag no other session on this machine's image store uses."""
    return uuid.uuid4().hex[:8]


def require_podman() -> None:
    """Fail in CI, skip elsewhere, when rootful Podman and debootstrap cannot be used here."""
    missing = [tool for tool in ("podman", "runc", "debootstrap") if shutil.which(tool) is None]
    problem = None
    if missing:
        problem = f"{', '.join(missing)} not installed; run as root: {INSTALL_HINT}"
    elif os.geteuid() != 0:
        problem = "the container tests need root (rootful Podman, debootstrap)"
    if problem is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(problem)
    pytest.skip(problem)


@dataclass(frozen=True)
class ContainerEngine:
    """Podman's Docker API for this session, and its CLI with the same configuration."""

    url: str
    env: dict[str, str]

    def client(self) -> DockerClient:
        return engine(self.url)

    def podman(self, *args: str, timeout: float = 600) -> str:
        done = subprocess.run(
            ["podman", *args], env=self.env, capture_output=True, text=True, timeout=timeout
        )
        if done.returncode != 0:
            pytest.fail(f"podman {' '.join(args)} failed:\n{done.stderr[-3000:]}")
        return done.stdout


@pytest.fixture(scope="session", name="container_engine")
def fixture_container_engine(
    registry: LocalRegistry, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[ContainerEngine]:
    """Podman's Docker-API service on a temporary socket, for the whole session."""
    require_podman()
    work = tmp_path_factory.mktemp("podman")
    registries = work / "registries.conf"
    registries.write_text(f'[[registry]]\nlocation = "{registry.domain}"\ninsecure = true\n')
    env = {
        **os.environ,
        "CONTAINERS_CONF": str(CONTAINERS_CONF),
        "CONTAINERS_REGISTRIES_CONF": str(registries),
    }
    url = f"unix://{work / 'podman.sock'}"
    log = work / "service.log"
    with log.open("ab") as out:
        # cwd: Podman 4's conmon drops an "oom" file into its working directory.
        service = subprocess.Popen(
            ["podman", "system", "service", "--time=0", url],
            cwd=work,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        session_engine = ContainerEngine(url=url, env=env)
        _wait_until_answering(session_engine, service, log)
        yield session_engine
    finally:
        service.terminate()
        try:
            service.wait(timeout=10)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()


def _wait_until_answering(
    session_engine: ContainerEngine, service: subprocess.Popen[bytes], log: Path
) -> None:
    deadline = time.monotonic() + _STARTUP_SECONDS
    while time.monotonic() < deadline and service.poll() is None:
        try:
            client = session_engine.client()
        except DockerException:
            time.sleep(0.1)
            continue
        client.close()
        return
    pytest.fail(f"podman system service did not answer:\n{log.read_text()[-3000:]}")


@dataclass
class PolicyImages:
    """Policy images built on the template and pushed to the registry, by name."""

    engine: ContainerEngine
    registry: LocalRegistry
    work: Path
    session: str
    published: dict[str, str] = field(default_factory=dict)

    def local_tag(self, name: str) -> str:
        return f"localhost/manieval-test/{name}:{self.session}"

    @property
    def template(self) -> str:
        """This session's name of the policy template (docs: examples/policy-template)."""
        return self.local_tag("template")

    def publish(self, name: str, policy_source: str) -> str:
        """Build the template with this `policy.py`, push it; the image's pinned reference."""
        return self.publish_built(
            name,
            f"FROM {self.template}\nCOPY policy.py /opt/policy/policy.py\n",
            {"policy.py": policy_source},
        )

    def publish_built(self, name: str, dockerfile: str, files: dict[str, str] | None = None) -> str:
        """Build this Dockerfile (with these files beside it), push it; its pinned reference."""
        if name in self.published:
            return self.published[name]
        context = self.work / name
        context.mkdir(exist_ok=True)
        for file_name, text in (files or {}).items():
            (context / file_name).write_text(text)
        (context / "Dockerfile").write_text(dockerfile)
        local = self.local_tag(name)
        # --no-cache: a cache hit would hand back another session's image ID.
        self.engine.podman("build", "--quiet", "--no-cache", "--tag", local, str(context))
        digest_file = context / "digest"
        remote = f"{self.registry.domain}/manieval-test/{name}"
        self.engine.podman(
            "push",
            "--quiet",
            "--tls-verify=false",
            "--digestfile",
            str(digest_file),
            local,
            f"docker://{remote}:latest",
        )
        pinned = f"{remote}@{digest_file.read_text().strip()}"
        self.published[name] = pinned
        return pinned


@pytest.fixture(scope="session", name="policy_images")
def fixture_policy_images(
    container_engine: ContainerEngine,
    registry: LocalRegistry,
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[PolicyImages]:
    """The base image (cached in Podman's store), the template image, and a way to publish."""
    built = subprocess.run(
        [str(BASE_BUILD)], env=container_engine.env, capture_output=True, text=True, timeout=900
    )
    if built.returncode != 0:
        pytest.fail(f"{BASE_BUILD} failed:\n{built.stderr[-3000:]}")
    work = tmp_path_factory.mktemp("policy-images")
    context = work / "template"
    shutil.copytree(TEMPLATE, context)
    # As the template's README says: the SDK is copied next to the Dockerfile.
    shutil.copytree(SDK, context / "manieval_sdk", ignore=shutil.ignore_patterns("__pycache__"))
    images = PolicyImages(
        engine=container_engine, registry=registry, work=work, session=session_tag()
    )
    # Cached: an equal build by another session is the same image under its own name.
    container_engine.podman(
        "build",
        "--quiet",
        "--build-arg",
        f"BASE={BASE_IMAGE}",
        "--tag",
        images.template,
        str(context),
    )
    yield images
    # The base and the template's image stay as the next session's cache; this session's names
    # go: the template's, the policies' and those they got from this session's registry.
    untag(container_engine.env, images.template)
    for name, pinned in images.published.items():
        untag(container_engine.env, images.local_tag(name), pinned)


def policy_containers(
    container_engine: ContainerEngine, *, submission: int, attempt: int
) -> list[Container]:
    """Every policy container of one attempt, running or not."""
    labels = [
        f"{LABEL_ROLE}={ROLE_POLICY}",
        f"{LABEL_SUBMISSION}={submission}",
        f"{LABEL_ATTEMPT}={attempt}",
    ]
    with closing(container_engine.client()) as client:
        containers: list[Container] = client.containers.list(all=True, filters={"label": labels})
    return containers
