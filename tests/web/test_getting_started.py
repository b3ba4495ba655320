"""The getting-started page: linked from the home, challenge and submit pages; its commands
filled in for this service; the contract generated from the suite; the downloads it names."""

from __future__ import annotations

import io
import subprocess
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.challenges.contract import condition_effect
from server.challenges.service import suite_of
from server.downloads.artifacts import source_dir, source_file
from server.kit.image_refs import ImageReference, ResolvedImage
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import Challenge
from server.registry.published import LOCAL_POLICY_BASE, POLICY_BASE_REPOSITORY
from server.submissions import start_page
from server.submissions.images import image_resolver
from testkit.factories import FakeRegistry, RecordingQueue, make_user
from tests.web.helpers import browser
from tests.web.start_commands import page_commands
from tests.web.test_web_push_commands import REGISTRY, app_client

REPO = Path(__file__).resolve().parents[2]

START = "/challenges/server-tiny/start"


@pytest.fixture
def registry_client(settings: Settings, sessions: sessionmaker[Session]) -> Iterator[TestClient]:
    with_registry = settings.model_copy(
        update={"registry_domain": REGISTRY, "allowed_registries": [REGISTRY]}
    )
    with app_client(with_registry, sessions) as c:
        yield c


@pytest.mark.parametrize("page", ["/", "/challenges/server-tiny", "/challenges/server-tiny/submit"])
def test_the_home_challenge_and_submit_pages_link_to_it(
    client: TestClient, db: Session, tiny: Challenge, page: str
) -> None:
    make_user(db, "alice")
    assert f'href="{START}"' in browser(client, "alice").get(page).text


def test_its_contract_is_the_suites(client: TestClient, tiny: Challenge) -> None:
    page = client.get(START)
    assert page.status_code == 200
    suite = suite_of(tiny)
    for task in suite.tasks:
        cells = f"<td>{task.obs_mode}</td><td>{task.control_mode}</td>"
        assert f'<th scope="row">{task.env_id}</th>{cells}' in page.text
        assert f'<td class="numeric">{task.max_episode_steps}</td>' in page.text
    for condition in suite.conditions:
        assert f"<strong>{condition.name}</strong> ({condition_effect(condition)})" in page.text


def test_an_anonymous_reader_is_told_to_register_with_a_placeholder_name(
    registry_client: TestClient, tiny: Challenge
) -> None:
    blocks = {b.step: b for b in page_commands(registry_client.get(START).text)}
    assert list(blocks) == [
        *("install", "account", "template", "simulator", "evaluate", "build", "push", "board")
    ]
    server = " --server http://testserver"
    assert blocks["account"].lines == [
        f"manieval register -u NAME --email you@example.org{server}",
        f"manieval login -u NAME{server}",
    ]
    assert blocks["evaluate"].needs == "simulator"
    assert blocks["push"].lines == ["manieval push my-policy:v1 --challenge server-tiny --wait"]


def test_a_signed_in_reader_gets_their_name_and_no_registration(
    registry_client: TestClient, db: Session, tiny: Challenge
) -> None:
    make_user(db, "alice")
    page = browser(registry_client, "alice").get(START).text
    account = next(b for b in page_commands(page) if b.step == "account")
    assert account.lines == ["manieval login -u alice --server http://testserver"]


def test_without_a_registry_it_says_where_images_go_instead(
    client: TestClient, tiny: Challenge
) -> None:
    page = client.get(START).text
    assert "push" not in [b.step for b in page_commands(page)]
    assert "runs no registry of its own" in page


def test_every_download_it_names_is_served(client: TestClient, tiny: Challenge) -> None:
    page = client.get(START).text
    urls = [
        word.removeprefix("http://testserver")
        for block in page_commands(page)
        for line in block.lines
        for word in line.split()
        if "/downloads/" in word or word.endswith("suite.yaml")
    ]
    assert len(urls) == 5, urls  # two wheels, the template, the source, the suite
    for url in urls:
        assert client.get(url).status_code == 200, url
    assert client.get(urls[-1]).text == tiny.suite_yaml


def test_the_slim_cli_wheel_leaves_the_server_side_out(client: TestClient) -> None:
    wheel = zipfile.ZipFile(
        io.BytesIO(client.get("/downloads/manieval_cli-0.1.0-py3-none-any.whl").content)
    )
    names = wheel.namelist()
    assert "manieval/push.py" in names
    assert "manieval/serve.py" not in names
    assert not [n for n in names if n.startswith(("server/", "worker/"))]
    info = "manieval_cli-0.1.0.dist-info"
    assert "manieval = manieval.__main__:main" in wheel.read(f"{info}/entry_points.txt").decode()
    metadata = wheel.read(f"{info}/METADATA").decode()
    assert "Requires-Dist: typer" in metadata
    assert "torch" not in metadata
    assert "fastapi" not in metadata


def test_the_template_unpacks_with_the_sdk_beside_its_dockerfile(client: TestClient) -> None:
    served = client.get("/downloads/policy-template.tar.gz")
    names = tarfile.open(fileobj=io.BytesIO(served.content)).getnames()
    assert {
        "my-policy/Dockerfile",
        "my-policy/policy.py",
        "my-policy/manieval_sdk/__init__.py",
    } <= set(names)


def test_the_build_pulls_the_base_the_registry_publishes_pinned(
    registry_client: TestClient, tiny: Challenge
) -> None:
    page = registry_client.get(START).text
    build = next(b for b in page_commands(page) if b.step == "build")
    assert len(build.lines) == 1, build.lines
    published = f"{REGISTRY}/{POLICY_BASE_REPOSITORY}@sha256:"
    assert build.lines[0].startswith(
        f"podman build --tls-verify=false --build-arg BASE={published}"
    )
    assert build.lines[0].endswith(" -t my-policy:v1 my-policy")
    assert "builds on the base this service publishes in its registry" in page


@pytest.mark.parametrize("registry", [False, True])
def test_without_a_published_base_the_build_makes_it_from_the_template(
    settings: Settings, sessions: sessionmaker[Session], tiny: Challenge, registry: bool
) -> None:
    """No registry, or one without the base (here: images refused, as the embedded default
    without its engine): the template's base/Dockerfile, built once, then the policy."""
    update = {"registry_domain": REGISTRY, "allowed_registries": [REGISTRY]} if registry else {}
    refusal = "podman is not installed" if registry else None
    with app_client(settings.model_copy(update=update), sessions, refusal=refusal) as client:
        page = client.get(START).text
    build = next(b for b in page_commands(page) if b.step == "build")
    assert build.lines == [
        f"podman build -t {LOCAL_POLICY_BASE} my-policy/base  # the base, once",
        "podman build -t my-policy:v1 my-policy",
    ]
    assert "made once from the template's <code>base/Dockerfile</code>" in page


def test_the_template_carries_the_base_dockerfile(client: TestClient) -> None:
    served = tarfile.open(
        fileobj=io.BytesIO(client.get("/downloads/policy-template.tar.gz").content)
    )
    carried = served.extractfile("my-policy/base/Dockerfile")
    assert carried is not None
    assert carried.read() == (REPO / "docker" / "policy-base" / "Dockerfile").read_bytes()
    policy = served.extractfile("my-policy/Dockerfile")
    assert policy is not None
    assert f"ARG BASE={LOCAL_POLICY_BASE}\n" in policy.read().decode()
    build = (REPO / "docker" / "policy-base" / "build.sh").read_text()
    assert f"image=${{MANIEVAL_BASE_IMAGE:-{LOCAL_POLICY_BASE}}}\n" in build  # the one name


def test_the_registry_is_asked_for_the_base_at_most_once_a_minute(
    settings: Settings, sessions: sessionmaker[Session], tiny: Challenge
) -> None:
    asked: list[str] = []

    class Counting(FakeRegistry):
        def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage:
            asked.append(str(ref))
            return super().resolve(ref, max_bytes=max_bytes)

    configured = settings.model_copy(
        update={"registry_domain": REGISTRY, "allowed_registries": [REGISTRY]}
    )
    app = create_app(
        configured,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=image_resolver(configured, Counting()),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app, base_url="http://testserver") as client:
        for _ in range(3):
            assert "--build-arg BASE=" in client.get(START).text
    assert len(asked) == 1, asked


def test_without_its_source_served_the_page_says_to_install_from_a_checkout(
    client: TestClient, tiny: Challenge, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(start_page, "served", dict)  # as the control-plane image: no source
    page = client.get(START).text
    assert "simulator" not in [b.step for b in page_commands(page)]
    assert "This service does not serve its source" in page


def test_the_source_is_what_make_install_needs_and_nothing_else(client: TestClient) -> None:
    served = client.get(f"/downloads/{source_file()}")
    assert served.status_code == 200
    archive = tarfile.open(fileobj=io.BytesIO(served.content))
    members = {m.name.removeprefix(f"{source_dir()}/"): m for m in archive.getmembers()}
    assert all(m.name.startswith(f"{source_dir()}/") for m in archive.getmembers())
    makefile = archive.extractfile(members["Makefile"])
    assert makefile is not None
    assert "\ninstall-evaluator:\n" in makefile.read().decode()
    for needed in ("pyproject.toml", "constraints.txt", "scripts/install-python.sh"):
        assert needed in members, needed
    assert "evaluator/evaluation.py" in members
    assert "suites/maniskill-core.yaml" in members
    assert members["scripts/system-deps.sh"].mode == 0o755  # make runs it
    assert members["docker/policy-base/build.sh"].mode == 0o755
    assert not [n for n in members if "__pycache__" in n or ".egg-info" in n or "/." in n]
    # Every part of the repository is served or left out on purpose: never a data directory,
    # a virtualenv or anything else that happens to lie beside the service.
    tracked = subprocess.run(
        ["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.split()
    left_out = {"tests", "testkit", "bench", ".ci", ".gitignore", ".dockerignore"}
    tops = {path.split("/")[0] for path in tracked}
    assert tops - left_out == {n.split("/")[0] for n in members}
    assert set(members) <= set(tracked)


def test_an_unknown_download_is_a_404(client: TestClient) -> None:
    assert client.get("/downloads/nothing.whl").status_code == 404
