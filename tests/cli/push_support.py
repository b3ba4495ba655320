"""A real `manieval serve` on embedded defaults with the registry and Podman it starts, and
the policy template built as its README says: shared by the CLI and the browser tests."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import uuid
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import yaml

from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from tests.cli.conftest import REPO, LiveServer, Participant, free_port, running_server
from tests.server.registry_fixture import require_tool
from tests.worker.container_fixtures import (
    BASE_BUILD,
    BASE_IMAGE,
    CONTAINERS_CONF,
    require_podman,
    untag,
)
from tests.worker.openpi_image import build_openpi_image, visual_track_in_small

TEMPLATE = REPO / "examples" / "policy-template"
SDK = REPO / "evaluator" / "sdk" / "manieval_sdk"
CHALLENGE = "push-tiny"
TINY_SUITE = """\
name: push-tiny
version: 1
description: One task, one episode.
tasks:
  - {env_id: PickCube-v1, max_episode_steps: 12, episodes: 1}
phases:
  dev: {description: Public seeds., seeds: {kind: public, start: 0}}
conditions:
  - {name: nominal, params: {kind: nominal}}
limits:
  connect_timeout_s: 60
  first_call_timeout_s: 60
  call_timeout_s: 5
  budget_s: 300
"""
# The visual track (maniskill-visual) in small: PickCube-v1 seen by its camera, one episode.
VISUAL_CHALLENGE = "push-visual"
VISUAL_SUITE = yaml.safe_dump(
    visual_track_in_small(VISUAL_CHALLENGE, episodes=1).model_dump(mode="json"), sort_keys=False
)


@dataclass(frozen=True)
class Embedded:
    server: LiveServer
    registry: str
    suite: Path
    work: Path

    def participant(self, name: str) -> Participant:
        return Participant(self.server.url, self.work / f"config-{name}")

    def engine_env(self, name: str) -> dict[str, str]:
        """The participant's own Podman (its logins in a file of its own), and the registry
        the service announces."""
        return {
            "REGISTRY_AUTH_FILE": str(self.work / f"auth-{name}.json"),
        }


def build_base_image() -> None:
    """Podman, docker-registry and the policy base image (built once, then cached)."""
    require_podman()
    require_tool("docker-registry")
    built = subprocess.run(
        [str(BASE_BUILD)],
        env={**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert built.returncode == 0, built.stderr[-3000:]


def data_with_challenge(
    work: Path, name: str, suite_text: str, options: ChallengeOptions
) -> tuple[Path, Path]:
    """A data directory (`work/data`) whose database holds the challenge of `suite_text`,
    written to `work/<name>.yaml`: (the data directory, the suite file)."""
    data = work / "data"
    suite = work / f"{name}.yaml"
    suite.write_text(suite_text)
    settings = Settings(dev_mode=True, data_dir=data, cookie_secure=False)
    upgrade(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    try:
        with session_factory(engine).begin() as db:
            load_challenge(db, suite, options, seed_secret=settings.secret("seed_secret"))
    finally:
        engine.dispose()
    return data, suite


@contextmanager
def embedded_service(
    work: Path, *, more_challenges: Mapping[str, str] | None = None
) -> Iterator[Embedded]:
    """`manieval serve` on embedded defaults: it starts the registry and Podman's API. Its
    challenges: `push-tiny`, and `more_challenges` (name: suite text)."""
    build_base_image()
    options = ChallengeOptions(quota_per_day=50, quota_concurrent=3)
    for name, text in (more_challenges or {}).items():
        data_with_challenge(work, name, text, options)
    data, suite = data_with_challenge(work, "push-tiny", TINY_SUITE, options)
    registry = f"127.0.0.1:{free_port()}"
    extra = {
        "MANIEVAL_EMBEDDED_REGISTRY": "true",
        "MANIEVAL_EMBEDDED_ENGINE": "true",
        "MANIEVAL_EMBEDDED_REGISTRY_ADDR": registry,
    }
    try:
        with running_server(data, challenges=False, extra=extra) as server:
            yield Embedded(server=server, registry=registry, suite=suite, work=work)
    finally:
        remove_images(registry, local=BUILT)
    assert not _alive(data / "registry" / "registry.pid")  # stopped with the server
    assert not _alive(data / "engine" / "podman.pid")


BUILT: list[str] = []  # local tags this module built
TAG = uuid.uuid4().hex[:8]  # sessions at once on one image store never share a name


INSPECT_NAMES = "{{json .RepoTags}} {{json .RepoDigests}}"
ENGINE_ENV = {**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)}


def remove_images(registry: str, *, local: list[str]) -> None:
    """Take out the names this module gave (its local tags) and those its registry's images got
    (pushed, pulled), by name only (`untag`): other sessions on the same image store may hold
    images of the same content under their own names."""
    untag(ENGINE_ENV, *local)
    listed = subprocess.run(
        ["podman", "images", "--format", "{{.ID}} {{.Repository}}"],
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout.splitlines()
    for image_id in {line.split()[0] for line in listed if f" {registry}/" in line}:
        names = subprocess.run(
            ["podman", "image", "inspect", "--format", INSPECT_NAMES, image_id],
            capture_output=True,
            text=True,
            timeout=60,
        ).stdout.split()
        references = [r for part in names for r in json.loads(part) if r.startswith(f"{registry}/")]
        untag(ENGINE_ENV, *references)


def _alive(pid_file: Path) -> bool:
    if not pid_file.exists():
        return False
    return Path(f"/proc/{pid_file.read_text().strip()}").exists()


def build_template(embedded: Embedded, tag: str) -> Path:
    """What the template's README says: copy it, add the SDK, `podman build`."""
    context = embedded.work / f"policy-{tag.replace('/', '-').replace(':', '-')}"
    shutil.copytree(TEMPLATE, context)
    shutil.copytree(SDK, context / "manieval_sdk", ignore=shutil.ignore_patterns("__pycache__"))
    done = subprocess.run(
        [
            "podman",
            "build",
            "--quiet",
            "--build-arg",
            f"BASE={BASE_IMAGE}",
            "-t",
            tag,
            str(context),
        ],
        env={**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    BUILT.append(tag)
    return context


def build_openpi(embedded: Embedded, tag: str) -> None:
    """The openpi server example's image, as its README builds it (cached layers)."""
    env = {**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)}
    build_openpi_image(env, embedded.work, tag=tag)
    BUILT.append(tag)
