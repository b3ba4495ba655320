"""Print the Python requirements of one ManiEval image, one per line, from pyproject.toml.

    python docker/requirements.py control-plane   # the server and the worker images
    python docker/requirements.py evaluator       # the evaluator image: everything

The dependencies stay listed in one place (pyproject.toml) and their versions in another
(constraints.txt, passed to pip with -c). The control plane (API, Celery worker and beat with
the Kubernetes executor) never simulates, so it leaves out the simulator stack, which is most
of an image's size (torch alone is several hundred MB). The participant SDK is not listed: it is
installed from evaluator/sdk. tests/deploy checks that the control plane imports without the
packages left out here.
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"
SDK = "manieval-sdk"
SIMULATOR_ONLY = frozenset(
    {"torch", "mani-skill", "sapien", "gymnasium", "imageio", "imageio-ffmpeg"}
)
ROLES = ("control-plane", "evaluator")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*")


def normalize(name: str) -> str:
    """PEP 503 normalized project name."""
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_name(requirement: str) -> str:
    """The normalized project name of a PEP 508 requirement string."""
    match = _NAME.match(requirement.strip())
    if match is None:
        raise ValueError(f"not a requirement: {requirement!r}")
    return normalize(match.group(0))


def requirements(role: str, pyproject: Path = PYPROJECT) -> list[str]:
    """The runtime requirements an image of `role` installs (besides the SDK)."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}: one of {', '.join(ROLES)}")
    with pyproject.open("rb") as f:
        dependencies: list[str] = tomllib.load(f)["project"]["dependencies"]
    left_out = {SDK} | (SIMULATOR_ONLY if role == "control-plane" else set())
    return [r for r in dependencies if requirement_name(r) not in left_out]


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] not in ROLES:
        sys.exit(f"usage: {sys.argv[0]} {'|'.join(ROLES)}")
    print("\n".join(requirements(sys.argv[1])))
