"""docker/: what every image is built from, who it runs as, and what goes into it.

No image registry is reachable here, so these images cannot be built in the tests (the policy
base can: test_policy_image.py). What can be checked without building them is checked here.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from types import ModuleType

import pytest

from tests.deploy.dockerfiles import (
    DOCKER,
    DOCKERFILES,
    copy_sources,
    dockerignore_patterns,
    effective_user,
    final_stages,
    ignored,
    instructions,
    stages,
)
from tests.deploy.manifests import REPO, container, render
from worker.containers import POLICY_UID
from worker.kubernetes.manifest import EVALUATOR_UID, SHARED_GID


def _load_requirements() -> ModuleType:
    """docker/requirements.py, the script the image builds run (docker/ is no package)."""
    spec = importlib.util.spec_from_file_location("docker_requirements", DOCKER / "requirements.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


requirements = _load_requirements()

PINNED = re.compile(r"^(docker\.io/)?[a-z0-9][^\s@]*@sha256:[0-9a-f]{64}$")
ROOT_CONTEXT = [p for p in DOCKERFILES if p.parent.name != "policy-base"]


def ids(path: Path) -> str:
    return path.parent.name


def test_every_image_has_its_dockerfile():
    names = {p.parent.name for p in DOCKERFILES}
    assert names == {"control-plane", "evaluator", "policy-base"}
    control_plane = stages(DOCKER / "control-plane" / "Dockerfile")
    assert [s.name for s in final_stages(control_plane)] == ["worker", "server"]  # server: default
    evaluator = stages(DOCKER / "evaluator" / "Dockerfile")
    assert [s.name for s in final_stages(evaluator)] == ["gpu", "cpu"]  # cpu: the default


@pytest.mark.parametrize("path", DOCKERFILES, ids=ids)
def test_every_base_image_is_pinned_by_digest(path: Path):
    earlier: set[str | None] = set()
    for stage in stages(path):
        assert stage.base in earlier or PINNED.match(stage.base), stage.base
        earlier.add(stage.name)


@pytest.mark.parametrize("path", DOCKERFILES, ids=ids)
def test_every_final_stage_runs_as_a_numeric_non_root_user(path: Path):
    all_stages = stages(path)
    for stage in final_stages(all_stages):
        user = effective_user(stage, all_stages)
        assert user is not None, f"{stage.name}: no USER"
        assert re.fullmatch(r"\d+:\d+", user), f"{stage.name}: USER {user} is not uid:gid"
        assert int(user.split(":")[0]) != 0


@pytest.mark.parametrize("path", DOCKERFILES, ids=ids)
def test_no_unpinned_build_frontend_is_fetched(path: Path):
    first = path.read_text().splitlines()[0]
    if first.replace(" ", "").lower().startswith("#syntax="):
        assert PINNED.match(first.split("=", 1)[1].strip()), first


@pytest.mark.parametrize("path", DOCKERFILES, ids=ids)
def test_nothing_is_fetched_by_add_and_every_pip_install_is_constrained(path: Path):
    for instruction in instructions(path):
        assert instruction.keyword != "ADD", "COPY only: ADD fetches URLs and unpacks archives"
        if "pip install" in instruction.args:
            assert "-c constraints" in instruction.args, instruction.args


def test_the_images_run_as_the_users_the_pods_name():
    for name in ("control-plane", "evaluator"):
        all_stages = stages(DOCKER / name / "Dockerfile")
        for stage in final_stages(all_stages):
            assert effective_user(stage, all_stages) == f"{EVALUATOR_UID}:{SHARED_GID}"
    objects = render("production")
    for kind, workload, name in [
        ("Deployment", "manieval-api", "api"),
        ("Deployment", "manieval-worker", "worker"),
        ("Deployment", "manieval-reconciler", "reconciler"),
        ("Job", "manieval-migrate", "migrate"),
    ]:
        context = container(objects, kind, workload, name)["securityContext"]
        assert (context["runAsUser"], context["runAsGroup"]) == (EVALUATOR_UID, SHARED_GID)
    (base,) = stages(DOCKER / "policy-base" / "Dockerfile")
    assert effective_user(base, [base]) == f"{POLICY_UID}:{POLICY_UID}"


def test_the_task_packages_image_builds_on_a_given_evaluator_under_its_pins_and_user():
    path = DOCKER / "evaluator" / "task-packages.Dockerfile"
    (stage,) = stages(path)
    # No default for the base: the evaluator's digest the service runs is given to the build.
    assert [i.args for i in instructions(path) if i.keyword in ("ARG", "FROM")] == [
        "EVALUATOR",
        "${EVALUATOR}",
    ]
    installs = [i.args for i in instructions(path) if "pip install" in i.args]
    assert installs
    assert all("cd /app;" in args and "-c constraints.txt" in args for args in installs)
    assert "ADD" not in [i.keyword for i in instructions(path)]
    assert effective_user(stage, [stage]) == f"{EVALUATOR_UID}:{SHARED_GID}"
    evaluator = stages(DOCKER / "evaluator" / "Dockerfile")
    assert [i for i in stage.instructions if i.keyword == "CMD"] == [
        i for i in final_stages(evaluator)[-1].instructions if i.keyword == "CMD"
    ]


def test_the_pods_run_the_image_built_for_them():
    # The worker image's command is Celery's worker; the reconciler is one too (with beat).
    for overlay in ("dev", "production"):
        objects = render(overlay)
        images = {
            name: container(objects, kind, name, c)["image"].split("@")[0].split(":")[0]
            for kind, name, c in [
                ("Deployment", "manieval-api", "api"),
                ("Job", "manieval-migrate", "migrate"),
                ("Deployment", "manieval-worker", "worker"),
                ("Deployment", "manieval-reconciler", "reconciler"),
            ]
        }
        assert images["manieval-api"] == images["manieval-migrate"]
        assert images["manieval-worker"] == images["manieval-reconciler"]
        assert images["manieval-worker"].endswith("worker"), overlay
        assert images["manieval-api"].endswith("server"), overlay
    worker_stage = next(
        s for s in stages(DOCKER / "control-plane" / "Dockerfile") if s.name == "worker"
    )
    (cmd,) = [i.args for i in worker_stage.instructions if i.keyword == "CMD"]
    assert cmd.startswith('["celery", "-A", "worker.celery_app", "worker"')


def needed_in_images() -> list[str]:
    """What the images run: the packages, the migrations, the bundled suites (and web/)."""
    with (REPO / "pyproject.toml").open("rb") as f:
        include = tomllib.load(f)["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = [pattern.rstrip("*") for pattern in include]
    extra = ["alembic", "alembic.ini", "suites", "evaluator/sdk/manieval_sdk", "web"]
    extra += ["docs/metrics.md"]  # served as /help/metrics
    extra += ["examples/policy-template", "docker/policy-base/Dockerfile"]  # the template download
    paths = [*packages, *extra]
    return [
        str(f.relative_to(REPO))
        for p in paths
        if (REPO / p).exists()
        for f in ([REPO / p] if (REPO / p).is_file() else (REPO / p).rglob("*"))
        if f.is_file() and "__pycache__" not in f.parts and ".egg-info" not in str(f)
    ]


def test_the_build_context_holds_what_the_images_run():
    patterns = dockerignore_patterns()
    needed = needed_in_images()
    assert "server/app.py" in needed
    assert "suites/maniskill-core.yaml" in needed
    assert [path for path in needed if ignored(path, patterns)] == []
    for path in ROOT_CONTEXT:
        for source in copy_sources(path):
            assert (REPO / source).exists(), source
            assert not ignored(source, patterns), f"{path}: COPY {source} is ignored"


@pytest.mark.parametrize(
    "path",
    [
        ".venv/bin/python",
        ".git/HEAD",
        "evaluator/sdk/.git/config",
        "tests/worker/test_containers.py",
        "tests/evaluator/tiny_suite.yaml",
        ".hypothesis/examples/x",
        ".mypy_cache/3.11/x.json",
        "server/__pycache__/app.cpython-311.pyc",
        "manieval.egg-info/PKG-INFO",
        "k8s/overlays/dev/secrets.yaml",
        "docs/deploy.md",
        "docker/control-plane/Dockerfile",
        "bench/leaderboard_load.py",
        "artifacts/run/video.mp4",
        "r.json",
        ".env",
        "deploy/tls.key",
    ],
)
def test_the_build_context_leaves_out_environments_vcs_tests_and_local_data(path: str):
    assert ignored(path, dockerignore_patterns())


def test_the_control_plane_leaves_the_simulator_out_and_the_evaluator_has_everything():
    with (REPO / "pyproject.toml").open("rb") as f:
        declared = tomllib.load(f)["project"]["dependencies"]
    names = {requirements.requirement_name(r) for r in declared}
    control_plane = {
        requirements.requirement_name(r) for r in requirements.requirements("control-plane")
    }
    evaluator = {requirements.requirement_name(r) for r in requirements.requirements("evaluator")}
    assert requirements.SIMULATOR_ONLY <= names
    assert control_plane == names - requirements.SIMULATOR_ONLY - {requirements.SDK}
    assert evaluator == names - {requirements.SDK}
    pinned = {
        requirements.normalize(line.split("==")[0])
        for line in (REPO / "constraints.txt").read_text().splitlines()
        if "==" in line
    }
    assert evaluator <= pinned, "every requirement is pinned by constraints.txt"


def test_the_requirements_script_prints_one_requirement_a_line():
    done = subprocess.run(
        [sys.executable, str(DOCKER / "requirements.py"), "control-plane"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert done.stdout.splitlines() == requirements.requirements("control-plane")
    bad = subprocess.run([sys.executable, str(DOCKER / "requirements.py"), "all"], check=False)
    assert bad.returncode != 0
