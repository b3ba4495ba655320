"""The files of /downloads, built from the sources this service runs: the participant SDK and
the slim `manieval` CLI as wheels (the same versions as the service's), the policy template
with the SDK inside, ready for `podman build`, and the service's own source, whose `make
install` brings the simulator for scoring a policy locally exactly as this service does."""

from __future__ import annotations

import gzip
import io
import os
import re
import subprocess
import tarfile
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, partial
from pathlib import Path
from typing import Any

from server.downloads.wheel import WheelSpec, build_wheel

REPO = Path(__file__).resolve().parents[2]
SDK_PROJECT = REPO / "evaluator" / "sdk"
CLI_PACKAGE = REPO / "manieval"
TEMPLATE = REPO / "examples" / "policy-template"
BASE_DOCKERFILE = REPO / "docker" / "policy-base" / "Dockerfile"  # the template's base/
TEMPLATE_FILE = "policy-template.tar.gz"
TEMPLATE_DIR = "my-policy"  # what the archive unpacks to
WHEEL_TYPE = "application/zip"
GZIP_TYPE = "application/gzip"
EPOCH_SECONDS = 315532800  # 1980-01-01, the wheels' zip time

# The CLI's modules that compose the service (they import the server, the worker or the
# simulator): left out of the slim CLI, whose `manieval serve`, `demo`, `db`, `admin`,
# `challenge` and `evaluate` say how to get them (manieval/cli.py).
SERVER_SIDE = frozenset(
    {
        "demo.py",
        "engines.py",
        "policy_base.py",
        "quiet.py",
        "serve.py",
        "service.py",
        "supervise.py",
    }
)
# The participant commands' third-party packages, pinned as the service's own pyproject pins
# them (names only here: the versions come from there).
CLI_REQUIRES = ("typer", "rich", "httpx", "platformdirs")
# The evaluator's pure-Python modules that a participant command uses (`manieval compare`).
CLI_EVALUATOR_MODULES = ("__init__.py", "paired.py", "stats.py")
# What the source download holds: what `make install` and `manieval evaluate` need, and of it
# only what git tracks, so that nothing else in the directory the service runs from (a data
# directory, a virtualenv, an operator's keys) is ever served; the suite, benchmarks, CI stay out.
SOURCE_FILES = ("Makefile", "README.md", "pyproject.toml", "constraints.txt", "alembic.ini")
SOURCE_DIRS = (
    *("alembic", "docker", "docs", "evaluator", "examples", "internal_api", "k8s", "manieval"),
    *("scripts", "server", "suites", "web", "worker"),
)
_NOT_SOURCE = re.compile(r"(^|/)(__pycache__|[^/]*\.egg-info|\.[^/]*)(/|$)|\.py[co]$")


class NotServed(LookupError):
    """A download this service does not have (its sources are not installed beside it)."""


@dataclass(frozen=True)
class Download:
    filename: str
    content: bytes
    media_type: str


def _project(pyproject: Path) -> dict[str, Any]:
    project: dict[str, Any] = tomllib.loads(pyproject.read_text())["project"]
    return project


def _package_files(
    root: Path, *, prefix: str, skip: frozenset[str] = frozenset()
) -> dict[str, bytes]:
    """Every .py and .typed file under `root`, by its path in the wheel."""
    files = {}
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root)
        if (
            path.is_file()
            and path.suffix in (".py", ".typed")
            and "__pycache__" not in relative.parts
        ):
            if relative.as_posix() not in skip:
                files[f"{prefix}/{relative.as_posix()}"] = path.read_bytes()
    return files


def _requirement_name(requirement: str) -> str:
    return re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0]


def sdk_spec() -> WheelSpec:
    """The participant SDK (package `manieval_sdk`), as its own pyproject declares it."""
    if not (SDK_PROJECT / "pyproject.toml").is_file():
        raise NotServed("the SDK's sources are not installed beside this service")
    project = _project(SDK_PROJECT / "pyproject.toml")
    return WheelSpec(
        name=str(project["name"]),
        version=str(project["version"]),
        summary=str(project["description"]),
        requires=[str(r) for r in project["dependencies"]],
        requires_python=str(project["requires-python"]),
        files=_package_files(SDK_PROJECT / "manieval_sdk", prefix="manieval_sdk"),
    )


def cli_spec() -> WheelSpec:
    """The slim `manieval` command (distribution `manieval-cli`): the participant commands,
    without the server's, the worker's or the simulator's packages."""
    if not (CLI_PACKAGE / "cli.py").is_file():
        raise NotServed("the CLI's sources are not installed beside this service")
    project = _project(REPO / "pyproject.toml")
    pinned = {_requirement_name(str(r)): str(r) for r in project["dependencies"]}
    return WheelSpec(
        name="manieval-cli",
        version=str(project["version"]),
        summary="The ManiEval participant command line (register, login, push, submit, follow)",
        requires=[pinned[name] for name in CLI_REQUIRES],
        requires_python=str(project["requires-python"]),
        files=_package_files(CLI_PACKAGE, prefix="manieval", skip=SERVER_SIDE)
        | {f"evaluator/{m}": (REPO / "evaluator" / m).read_bytes() for m in CLI_EVALUATOR_MODULES},
        scripts={"manieval": "manieval.__main__:main"},
    )


def template_archive() -> bytes:
    """The policy template with the SDK beside its Dockerfile and the base's Dockerfile in
    `base/`, as `my-policy/`."""
    if not (TEMPLATE.is_dir() and BASE_DOCKERFILE.is_file()):
        raise NotServed("the policy template is not installed beside this service")
    files = {
        f"{TEMPLATE_DIR}/{p.relative_to(TEMPLATE).as_posix()}": p.read_bytes()
        for p in sorted(TEMPLATE.rglob("*"))
        if p.is_file() and "__pycache__" not in p.parts
    }
    files |= _package_files(SDK_PROJECT / "manieval_sdk", prefix=f"{TEMPLATE_DIR}/manieval_sdk")
    files[f"{TEMPLATE_DIR}/base/Dockerfile"] = BASE_DOCKERFILE.read_bytes()
    return _tar_gz({path: (data, 0o644) for path, data in files.items()})


@cache
def source_dir() -> str:
    """What the source download unpacks to: `manieval-VERSION`."""
    return f"manieval-{_project(REPO / 'pyproject.toml')['version']}"


def source_file() -> str:
    return f"{source_dir()}.tar.gz"


def tracked_source(root: Path = REPO) -> list[str]:
    """The files of the source download, relative to `root`: those git tracks under
    :data:`SOURCE_FILES` and :data:`SOURCE_DIRS` (never an ignored or untracked file lying
    there), regular files only. Raises :class:`NotServed` outside a git checkout."""
    if not (root / "Makefile").is_file():
        raise NotServed("the service's source is not installed beside it")
    try:
        listed = subprocess.run(
            ["git", "-C", str(root), "ls-files", "-z", "--", *SOURCE_FILES, *SOURCE_DIRS],
            capture_output=True,
            timeout=60,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NotServed(f"git cannot list the service's source: {exc}") from None
    if listed.returncode != 0:
        raise NotServed("the service does not run from a git checkout of its source")
    names = [name for name in listed.stdout.decode("utf-8", "replace").split("\0") if name]
    return [
        name
        for name in names
        if not _NOT_SOURCE.search(name)
        and (root / name).is_file()
        and not (root / name).is_symlink()
    ]


def source_archive(root: Path = REPO) -> bytes:
    """The service's own source (:func:`tracked_source`) as `manieval-VERSION/`, executables
    kept executable."""
    files = {}
    for name in tracked_source(root):
        path = root / name
        mode = 0o755 if os.access(path, os.X_OK) else 0o644
        files[f"{source_dir()}/{name}"] = (path.read_bytes(), mode)
    return _tar_gz(files)


def _tar_gz(files: dict[str, tuple[bytes, int]]) -> bytes:
    """A gzipped tar of `files` (path: content and mode), sorted, its times fixed (the gzip
    header's too): the same bytes on every build, as the wheels."""
    out = io.BytesIO()
    with (
        gzip.GzipFile(fileobj=out, mode="wb", mtime=0) as zipped,
        tarfile.open(fileobj=zipped, mode="w", format=tarfile.PAX_FORMAT) as archive,
    ):
        for path, (data, mode) in sorted(files.items()):
            member = tarfile.TarInfo(path)
            member.size, member.mode, member.mtime = len(data), mode, EPOCH_SECONDS
            archive.addfile(member, io.BytesIO(data))
    return out.getvalue()


@cache
def wheel_files() -> tuple[str, ...]:
    """The wheels' file names, the SDK's first: what the getting-started page installs."""
    return tuple(spec().filename for spec in (sdk_spec, cli_spec))


@cache
def served() -> dict[str, tuple[Callable[[], bytes], str]]:
    """What this service serves, by file name: how each is built, and its media type. Only
    the sources are looked at here; each file is built when first asked for."""
    found: dict[str, tuple[Callable[[], bytes], str]] = {}
    for spec in (sdk_spec, cli_spec):
        try:
            wheel = spec()
        except NotServed:
            continue
        found[wheel.filename] = (partial(build_wheel, wheel), WHEEL_TYPE)
    if TEMPLATE.is_dir() and BASE_DOCKERFILE.is_file():
        found[TEMPLATE_FILE] = (template_archive, GZIP_TYPE)
    try:
        if tracked_source():
            found[source_file()] = (source_archive, GZIP_TYPE)
    except NotServed:
        pass
    return found


def served_download(filename: str) -> Download | None:
    """One download, built once per process (from the running sources), or None."""
    return _built(filename) if filename in served() else None


@cache
def _built(filename: str) -> Download:  # only names served() knows: a bounded cache
    build, media_type = served()[filename]
    return Download(filename, build(), media_type)
