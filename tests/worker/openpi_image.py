"""The example openpi server's policy image (examples/policies/openpi-server), built as its
README says: the example, the SDK and the pinned wheels of openpi-client and websockets in one
build context, on the policy base image.

The wheels are downloaded by pip once per set of pins into the virtualenv (the image build has
no network), and Podman's layer cache keeps the image: a second build takes seconds. Used by
tests/worker/test_openpi_image.py (the docker executor) and tests/cli/test_push.py (pushed to
the embedded default and ranked).
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

import pytest

from evaluator.suite import ActionChunks, Suite, load_suite
from tests.worker.container_fixtures import BASE_IMAGE, REPO, SDK

EXAMPLE = REPO / "examples" / "policies" / "openpi-server"
REQUIREMENTS = EXAMPLE / "requirements.txt"
UNWANTED = shutil.ignore_patterns("__pycache__", "wheels", "manieval_sdk")


def openpi_wheels() -> Path:
    """The wheels requirements.txt pins, checked against their hashes by pip."""
    pins = hashlib.sha256(REQUIREMENTS.read_bytes()).hexdigest()[:12]
    wheels = Path(sys.prefix) / "openpi-wheels" / pins
    if wheels.is_dir():
        return wheels
    wheels.parent.mkdir(parents=True, exist_ok=True)
    download = Path(tempfile.mkdtemp(dir=wheels.parent, prefix=".download-"))
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--quiet",
            "--no-deps",
            "--only-binary=:all:",
            "--platform",
            "any",
            "--python-version",
            "3.11",
            "--require-hashes",
            "-r",
            str(REQUIREMENTS),
            "-d",
            str(download),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0:
        shutil.rmtree(download, ignore_errors=True)
        pytest.fail(f"pip could not download the openpi wheels:\n{done.stderr[-3000:]}")
    try:
        download.rename(wheels)  # whole or not at all; another session may have been first
    except OSError:
        shutil.rmtree(download, ignore_errors=True)
    return wheels


def build_openpi_image(env: Mapping[str, str], work: Path, *, tag: str) -> str:
    """The example's image, tagged `tag` (a name of the caller's session only: tests on one
    image store never re-tag a shared name), on the policy base image (which must exist)."""
    context = work / "openpi-server-context"
    shutil.rmtree(context, ignore_errors=True)
    shutil.copytree(EXAMPLE, context, ignore=UNWANTED)
    shutil.copytree(SDK, context / "manieval_sdk", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(openpi_wheels(), context / "wheels")
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
        env=dict(env),
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0:
        pytest.fail(f"podman build of the openpi example failed:\n{done.stderr[-3000:]}")
    return tag


def visual_track_in_small(
    name: str, *, episodes: int, action_chunks: ActionChunks | None = None
) -> Suite:
    """maniskill-visual as it is (rgbd, its observation keys, its instructions, its limits) but
    small: PickCube-v1 only, under its nominal condition, `episodes` episodes of 12 steps on its
    public seeds, nothing filmed; with these action chunks where given."""
    visual = load_suite("maniskill-visual")
    task = visual.task("PickCube-v1").model_copy(
        update={"max_episode_steps": 12, "episodes": episodes}
    )
    small = visual.model_copy(
        update={
            "name": name,
            "description": "The visual track (maniskill-visual) in small.",
            "tasks": (task,),
            "conditions": (visual.condition("nominal"),),
            "phases": {"dev": visual.phase("dev")},
            "videos": 0,
            **({"action_chunks": action_chunks} if action_chunks else {}),
        }
    )
    return Suite.model_validate(small.model_dump())
