"""Task packages: Python packages a suite names (`packages: [my_lab_tasks]`) that register
ManiSkill environments when imported (docs/task-packages.md).

They are the organizers' code, trusted like the suite: the evaluator imports them before it
makes environments, in its own processes; a policy's process never does. A package's version
is its distribution's (`importlib.metadata`), or for a module that is no installed distribution
(a directory on PYTHONPATH) a hash of its files, so that a changed task changes the suite's hash.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.util
import json
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from evaluator.suite import Suite, SuiteError

SOURCE_PREFIX = "src:"
"""How the version of a package that is no installed distribution begins: `src:` and the first
16 hex digits of the SHA-256 of its files (an editable install adds it after its version)."""
BUILTIN = "mani_skill"
"""How a task ManiSkill itself registers names its provider."""


class TaskPackageError(SuiteError):
    """A suite's task package is missing, fails to import, registers no task the suite runs,
    or is not the version the suite was loaded with."""


@dataclass(frozen=True)
class Resolution:
    """A suite's packages as this process imports them: each one's version, and the package
    (or `mani_skill`) that registers each task."""

    versions: dict[str, str]
    providers: dict[str, str]


def import_package(name: str) -> None:
    """Import one task package; TaskPackageError says what is missing and how to install it."""
    try:
        importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (name == exc.name or name.startswith(f"{exc.name}.")):
            raise TaskPackageError(missing(name)) from None
        raise TaskPackageError(f"task package {name!r} failed to import: {exc}") from None
    except Exception as exc:  # the organizer's code: any error is theirs to read
        raise TaskPackageError(
            f"task package {name!r} failed to import: {type(exc).__name__}: {exc}"
        ) from None


def missing(name: str) -> str:
    """What to do about a task package this Python cannot import."""
    return (
        f"task package {name!r} is not installed in this Python environment "
        f"({sys.executable}): install it into it with "
        f"`{sys.executable} -m pip install <{name}'s distribution or source directory>`, "
        f"or put the directory that holds it on PYTHONPATH; on Kubernetes, build the "
        f"evaluator image with it (docs/task-packages.md)"
    )


@functools.cache
def installed_version(name: str) -> str:
    """The version of an importable task package: its distribution's, with a hash of its files
    when it is installed editable; `src:<hash>` when it is no distribution at all. Cached per
    process: a module is imported once, so what it was when first asked is what runs."""
    top = name.split(".", 1)[0]
    distributions = metadata.packages_distributions().get(top, [])
    if distributions:
        distribution = metadata.distribution(distributions[0])
        if not _editable(distribution):
            return distribution.version
        return f"{distribution.version} {SOURCE_PREFIX}{source_hash(top)}"
    return f"{SOURCE_PREFIX}{source_hash(top)}"


def _editable(distribution: metadata.Distribution) -> bool:
    text = distribution.read_text("direct_url.json")
    if not text:
        return False
    try:
        return bool(json.loads(text).get("dir_info", {}).get("editable"))
    except (ValueError, AttributeError):
        return False


def source_hash(top: str) -> str:
    """The first 16 hex digits of the SHA-256 of a top-level module's files: every file below
    a package's directory (code and assets) but compiled bytecode, by relative path."""
    spec = importlib.util.find_spec(top)
    if spec is None:
        raise TaskPackageError(missing(top))
    roots = list(spec.submodule_search_locations or [])
    files: list[tuple[str, Path]] = []
    if roots:
        for root in map(Path, roots):
            files += [
                (f"{root.name}/{p.relative_to(root).as_posix()}", p)
                for p in root.rglob("*")
                if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"
            ]
    elif spec.origin:
        files = [(Path(spec.origin).name, Path(spec.origin))]
    digest = hashlib.sha256()
    for relative, path in sorted(files):
        digest.update(relative.encode() + b"\0" + hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()[:16]


def import_packages(pins: Mapping[str, str | None]) -> dict[str, str]:
    """Import the packages of an evaluation (name: the version its suite was loaded with, None:
    any) and return each one's version here; TaskPackageError on a different version."""
    found = {}
    for name, pinned in pins.items():
        import_package(name)
        found[name] = installed_version(name)
        if pinned is not None and found[name] != pinned:
            raise TaskPackageError(
                f"task package {name!r} is {found[name]} here, but the suite was loaded with "
                f"{pinned}: install that version where the evaluator runs (on Kubernetes, the "
                f"evaluator image), or load the suite again to evaluate with this one"
            )
    return found


def resolve(suite: Suite) -> Resolution:
    """Import ManiSkill's tasks and the suite's packages, and find each task's provider:
    TaskPackageError names a missing package, a failing one, or a task nobody registers."""
    versions = import_packages(dict.fromkeys(suite.packages))  # a missing one: said at once
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (ManiSkill's own tasks)

    providers = {}
    for task in suite.tasks:
        if task.env_id not in gym.registry:
            named = ", ".join(suite.packages) or "none"
            raise TaskPackageError(
                f"task {task.env_id!r} is registered neither by ManiSkill nor by the suite's "
                f"packages ({named}); registered by them: "
                f"{', '.join(registered_by(suite.packages)) or 'nothing'}"
            )
        providers[task.env_id] = provider(task.env_id, suite.packages)
    return Resolution(versions=versions, providers=providers)


def provider(env_id: str, packages: Iterable[str]) -> str:
    """The named package whose module defines the registered task (else the module's top-level
    package: `mani_skill` for ManiSkill's own)."""
    module = _module_of(env_id)
    for name in packages:
        if module == name or module.startswith(f"{name}."):
            return name
    return module.split(".", 1)[0]


def registered_by(packages: Iterable[str]) -> list[str]:
    """The task ids whose classes live in these packages, sorted."""
    import gymnasium as gym

    names = tuple(packages)
    return sorted(
        env_id for env_id in gym.registry if "/" not in env_id and provider(env_id, names) in names
    )


def _module_of(env_id: str) -> str:
    from gymnasium import registry
    from mani_skill.utils.registration import REGISTERED_ENVS

    if env_id in REGISTERED_ENVS:
        return str(REGISTERED_ENVS[env_id].cls.__module__)
    entry = registry[env_id].entry_point
    if isinstance(entry, str):
        return entry.split(":", 1)[0]
    return str(getattr(entry, "__module__", "") or "")


def simulator_installed() -> bool:
    """Whether this process can import ManiSkill (the control plane's images leave it out)."""
    return importlib.util.find_spec("mani_skill") is not None


def pin(suite: Suite) -> tuple[Suite, Resolution | None]:
    """The suite with every package's version pinned (`package_versions`), as it is loaded:
    resolved here (TaskPackageError if a stated version differs from the installed one); where
    ManiSkill is not installed, the versions must be stated, and the tasks are not resolved."""
    if not suite.packages:
        return suite, None
    if not simulator_installed():
        if not suite.package_versions:
            raise TaskPackageError(
                f"suite {suite.name!r} names task packages ({', '.join(suite.packages)}) and "
                "ManiSkill is not installed here to import them: state their versions in the "
                "suite's `package_versions` (`manieval challenge packages SUITE`, run in the "
                "evaluator image, prints them), or load it where the packages are installed"
            )
        return suite, None
    resolution = resolve(suite)
    for name, stated in suite.package_versions.items():
        if resolution.versions[name] != stated:
            raise TaskPackageError(
                f"task package {name!r} is {resolution.versions[name]} here, but the suite "
                f"states {stated} (package_versions)"
            )
    pinned = suite.model_copy(update={"package_versions": resolution.versions})
    return pinned, resolution
