"""What produced a result: the environment that decides its scores, the evaluator's code, the
policy's image, the machines and the scoring settings (docs/metrics.md, Provenance).

`environment` is the one definition of an evaluation environment: the evaluator records it
with every result, and the server computes the one it would evaluate in now with it, to mark
board entries evaluated in another. Nothing here fails an evaluation: what cannot be found out
(a package the control plane does not install, a GPU, a commit) is null.
"""

from __future__ import annotations

import functools
import os
import platform
import re
import shutil
import subprocess
from collections.abc import Iterable, Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from evaluator.packages import installed_version
from evaluator.plan import EvaluationPlan
from evaluator.results import (
    Environment,
    EvaluatorBuild,
    Machine,
    Provenance,
    ScoringSettings,
    Versions,
)

EVALUATOR_IMAGE_ENV = "MANIEVAL_EVALUATOR_IMAGE"
"""Set by the Kubernetes Job to the evaluator's own image (`worker.kubernetes.manifest`)."""
ROOT = Path(__file__).resolve().parent.parent
"""The repository (or the image's /app): pyproject.toml, constraints.txt and, in a checkout,
.git."""
ENVIRONMENT_PACKAGES = ("mani_skill", "sapien", "torch", "numpy")
"""The packages whose versions are part of the environment: those that simulate."""
COMPARED = (*ENVIRONMENT_PACKAGES, "sim_backend", "render_backend", "suite_sha256")
"""The environment's fields, in the order a difference is named."""
_CPU_KEYS = ("model name", "Model", "Hardware", "cpu model", "Processor")
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;#]+)")
_LOCAL_LABEL = re.compile(r"\+.*$")


def render_backend(sim_backend: str) -> str:
    """The renderer the evaluator uses with a simulation backend (`evaluator.sim.make_env`)."""
    return "sapien_cpu" if sim_backend == "physx_cpu" else "gpu"


def environment(*, suite_sha256: str, sim_backends: Iterable[str]) -> Environment:
    """The environment a suite (by its hash and its tasks' backends) is evaluated in by this
    installation: the simulating packages installed here, or where they are not (the control
    plane), the versions constraints.txt pins for the evaluator image."""
    backends = sorted(set(sim_backends))
    versions = {name: package_version(name) for name in ENVIRONMENT_PACKAGES}
    torch = versions["torch"]
    return Environment(
        mani_skill=versions["mani_skill"],
        sapien=versions["sapien"],
        # The local label names the wheel's build (+cpu, +cu128), not what it computes.
        torch=_LOCAL_LABEL.sub("", torch) if torch is not None else None,
        numpy=versions["numpy"],
        sim_backend="+".join(backends),
        render_backend="+".join(sorted({render_backend(b) for b in backends})),
        suite_sha256=suite_sha256,
    )


RecordedEnvironment = dict[str, str | list[str | None] | None]
"""An environment as a result records it (`recorded_environment`): a field on which shards
differed holds every shard's value; one the document does not record is absent."""


def recorded_environment(document: Mapping[str, Any]) -> RecordedEnvironment:
    """The environment a stored result document (of any schema version, as JSON) was
    evaluated in: its provenance's, or for a document older than 1.2, what its versions and
    suite say (no numpy, no backends)."""
    provenance = document.get("provenance")
    if isinstance(provenance, dict) and isinstance(provenance.get("environment"), dict):
        found: RecordedEnvironment = {
            k: v for k, v in provenance["environment"].items() if k in COMPARED
        }
        found.update(provenance.get("shard_differences") or {})
        return found
    versions = document.get("versions") or {}
    found = {name: versions.get(name) for name in ("mani_skill", "sapien", "torch")}
    torch = found["torch"]
    found["torch"] = _LOCAL_LABEL.sub("", torch) if isinstance(torch, str) else None
    found["suite_sha256"] = (document.get("suite") or {}).get("sha256")
    return {k: v for k, v in found.items() if v not in (None, "unknown")}


def differences(recorded: Mapping[str, object], current: Environment) -> list[str]:
    """The fields on which a recorded environment differs from the current one: a field
    either side does not know is not compared, and one on which shards differed differs
    when any shard's value does."""
    found = []
    for name in COMPARED:
        now = getattr(current, name)
        then = recorded.get(name)
        values = then if isinstance(then, list) else [then]
        if now is not None and any(v is not None and v != now for v in values):
            found.append(name)
    return found


def package_version(name: str) -> str | None:
    """A package's installed version, else the version constraints.txt pins, else None."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return _pinned_versions().get(_normalize(name))


@functools.cache
def _pinned_versions() -> dict[str, str]:
    try:
        lines = (ROOT / "constraints.txt").read_text(encoding="utf-8").splitlines()
    except OSError:
        return {}
    found = (_PIN.match(line.strip()) for line in lines)
    return {_normalize(m.group(1)): m.group(2) for m in found if m}


def _normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def manieval_version() -> str:
    """ManiEval's version: its installed metadata, else pyproject.toml's (the images run it
    from /app without installing it), else "unknown"."""
    try:
        return metadata.version("manieval")
    except metadata.PackageNotFoundError:
        pass
    try:
        text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    except OSError:
        return "unknown"
    found = re.search(r'^version\s*=\s*"([^"]+)"', text, re.MULTILINE)
    return found.group(1) if found else "unknown"


def installed_versions() -> Versions:
    """Versions of everything that decides the numbers (a package missing here: "unknown")."""
    return Versions(
        manieval=manieval_version(),
        mani_skill=package_version("mani_skill") or "unknown",
        sapien=package_version("sapien") or "unknown",
        torch=package_version("torch") or "unknown",
        python=platform.python_version(),
    )


@functools.cache
def git_commit() -> str | None:
    """The commit checked out where the code runs from, or None (not a checkout, no git)."""
    if not (ROOT / ".git").exists():
        return None
    commit = (_output(["git", "-C", str(ROOT), "rev-parse", "HEAD"]) or "").strip()
    return commit if re.fullmatch(r"[0-9a-f]{40,64}", commit) else None


def _output(command: list[str]) -> str | None:
    """What `command` prints, or None when it is not installed or fails (within 10 s)."""
    if shutil.which(command[0]) is None:
        return None
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout


def evaluator_build() -> EvaluatorBuild:
    """This evaluator's version, commit and (in a Kubernetes Job) image."""
    image = os.environ.get(EVALUATOR_IMAGE_ENV) or None
    return EvaluatorBuild(manieval=manieval_version(), commit=git_commit(), image=image)


@functools.cache
def machine() -> Machine:
    """This machine's CPU model and GPUs (null where there are none or they cannot be read)."""
    return Machine(cpu=cpu_model(), gpu=gpu_names())


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str | None:
    """The CPU's model name from /proc/cpuinfo (x86 and ARM name it differently), else what
    the platform says."""
    try:
        lines = cpuinfo.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        lines = []
    fields: dict[str, str] = {}
    for line in lines:
        key, sep, value = line.partition(":")
        if sep and value.strip():
            fields.setdefault(key.strip(), value.strip())
    for key in _CPU_KEYS:
        if key in fields:
            return fields[key]
    return platform.processor() or platform.machine() or None


def gpu_names() -> str | None:
    """The NVIDIA GPUs this process sees, as nvidia-smi names them ("2 x NVIDIA H100 ..."),
    or None without nvidia-smi or GPUs. Never CUDA itself: initialising it here would break
    the simulator processes forked after."""
    listed = _output(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"]) or ""
    names = [line.strip() for line in listed.splitlines() if line.strip()]
    counted = {name: names.count(name) for name in names}
    described = [name if n == 1 else f"{n} x {name}" for name, n in counted.items()]
    return ", ".join(described) or None


def scoring_settings(plan: EvaluationPlan) -> ScoringSettings:
    """The plan's settings that change scores."""
    return ScoringSettings(
        ignore_terminations=plan.ignore_terminations,
        control_mode={run.env_id: run.control_mode for run in plan.runs},
        max_episode_steps={run.env_id: run.max_episode_steps for run in plan.runs},
        action_chunk_max=plan.action_chunks.max_length,
        action_chunk_execute=plan.action_chunks.executed,
    )


def local_provenance(plan: EvaluationPlan, *, policy_image: str | None) -> Provenance:
    """The provenance of `plan` evaluated in this process, on this machine."""
    return Provenance(
        environment=environment(
            suite_sha256=plan.suite.sha256, sim_backends=(run.sim_backend for run in plan.runs)
        ),
        suite_version=plan.suite.version,
        evaluator=evaluator_build(),
        policy_image=policy_image,
        machines=[machine()],
        settings=scoring_settings(plan),
        packages={name: installed_version(name) for name in plan.packages},
    )


def merge(shards: Sequence[Provenance]) -> Provenance:
    """One provenance for the shards of one evaluation, in shard order: the first shard's,
    with every distinct machine, and each environment field on which any shard differed
    listed with every shard's value. Scores do not depend on it: it is merged beside them."""
    if not shards:
        raise ValueError("no shard provenance to merge")
    first = shards[0]
    machines: list[Machine] = []
    for shard in shards:
        machines += [m for m in shard.machines if m not in machines]
    differing = {
        name: [getattr(s.environment, name) for s in shards]
        for name in COMPARED
        if len({getattr(s.environment, name) for s in shards}) > 1
    }
    return first.model_copy(
        update={"machines": machines, "shards": len(shards), "shard_differences": differing}
    )
