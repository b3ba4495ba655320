"""The server and worker images leave the simulator out (docker/requirements.py): the control
plane must run without it. Checked in a Python whose imports of every distribution those images
lack fail, doing what the images' pods do: serve, migrate, and build an evaluation's Job."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.deploy.dockerfiles import DOCKER
from tests.deploy.manifests import REPO

POLICY = f"registry.example.org/alice/policy@sha256:{'ab' * 32}"
SECRET = "a-test-secret-of-at-least-thirty-two-characters"

SCRIPT = textwrap.dedent(
    """
    import importlib.abc, json, os, sys

    BLOCKED = set(json.loads(os.environ["BLOCKED_MODULES"]))

    class NotInTheImage(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"{name} is not in the control-plane image", name=name)
            return None

    sys.meta_path.insert(0, NotInTheImage())
    try:
        import torch
    except ModuleNotFoundError:
        pass
    else:
        raise SystemExit("the blocker let torch through")

    import server.cli, manieval.cli, manieval.serve, worker.celery_app, worker.run
    import worker.reconcile, worker.embedded
    from manieval.service import Service
    from server.app import create_app
    from server.kit.settings import Settings

    create_app(Settings(), background=False)
    Service(Settings(), port=8000)  # what `manieval serve` runs, composed but not started

    from evaluator.plan import build_plan
    from evaluator.suite import SUITES_DIR, load_suite
    from internal_api.schemas import Assignment
    from worker.kubernetes.spec import job_spec
    from worker.kubernetes.manifest import build_job
    from worker.settings import WorkerSettings

    suite = load_suite("maniskill-core")
    plan = build_plan(suite, "dev")
    handed = Assignment(
        submission_id=1,
        attempt=1,
        image=os.environ["POLICY"],
        plan=plan,
        suite_yaml=(SUITES_DIR / "maniskill-core.yaml").read_text(),
        shards=max(1, min(suite.shards, plan.episode_count())),
    )
    build_job(job_spec(WorkerSettings(), handed))

    from alembic.config import main
    main(["-c", "alembic.ini", "upgrade", "head"])
    print("control plane ok", sorted(m for m in BLOCKED if m in sys.modules))
    """
)


def _load(path: Path, name: str):  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def closure(requirements: list[str]) -> set[str]:
    """The distributions these requirements install, by name: their dependencies, with extras
    and environment markers applied as pip would."""
    seen: set[str] = set()
    pending = [Requirement(r) for r in requirements]
    while pending:
        requirement = pending.pop()
        name = canonicalize_name(requirement.name)
        key = f"{name}[{','.join(sorted(requirement.extras))}]"
        if key in seen:
            continue
        seen.add(key)
        seen.add(name)
        for text in metadata.distribution(name).requires or []:
            dependency = Requirement(text)
            wanted = dependency.marker is None or any(
                dependency.marker.evaluate({"extra": extra}) for extra in [*requirement.extras, ""]
            )
            if wanted:
                pending.append(dependency)
    return {name for name in seen if "[" not in name}


def blocked_modules() -> list[str]:
    """Top-level modules installed here that the control-plane images do not have."""
    requirements = _load(DOCKER / "requirements.py", "docker_requirements")
    installed = closure([*requirements.requirements("control-plane"), "manieval-sdk"])
    installed.add("manieval")  # our own code: copied into the image, not installed
    installed |= {"pip", "setuptools"}  # what `python -m venv` puts in every virtualenv
    return sorted(
        module
        for module, distributions in metadata.packages_distributions().items()
        if not any(canonicalize_name(d) in installed for d in distributions)
    )


def test_the_simulator_and_its_dependencies_are_what_is_left_out():
    blocked = set(blocked_modules())
    assert {"torch", "mani_skill", "sapien", "gymnasium", "cv2", "scipy"} <= blocked
    assert not {"fastapi", "celery", "kubernetes", "sqlalchemy", "psycopg", "numpy"} & blocked


def test_the_control_plane_serves_migrates_and_builds_jobs_without_the_simulator(tmp_path):
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")},
        "BLOCKED_MODULES": json.dumps(blocked_modules()),
        "POLICY": POLICY,
        "MANIEVAL_DATA_DIR": str(tmp_path),
        "MANIEVAL_DATABASE_URL": f"sqlite:///{tmp_path / 'manieval.db'}",
        "MANIEVAL_SECRET_KEY": SECRET,
        "MANIEVAL_SEED_SECRET": SECRET,
        "MANIEVAL_WORKER_TOKEN": SECRET,
        "MANIEVAL_QUEUE": "celery",
        "MANIEVAL_EXECUTOR": "kubernetes",
        "MANIEVAL_EVALUATOR_IMAGE": POLICY,
    }
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    assert "control plane ok []" in done.stdout
    assert (tmp_path / "manieval.db").exists()
