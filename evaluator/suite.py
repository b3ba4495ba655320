"""Benchmark suites as data: tasks, phases with their seeds, stress conditions and limits."""

from __future__ import annotations

import hashlib
import hmac
import json
import re
from keyword import iskeyword
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

SUITES_DIR = Path(__file__).resolve().parent.parent / "suites"
SEED_LIMIT = 1 << 31  # seeds are non-negative int32, as ManiSkill and numpy expect
OBS_MODE_PATTERN = r"^[a-z_]+(\+[a-z_]+)*$"  # ManiSkill's modes: state_dict, rgbd, rgb+depth...
FLAT_OBS_MODES = frozenset({"state"})  # one array, no named entries
# An observation entry's path: names joined by "/", where "*" in a name matches any characters.
OBS_KEY_PATTERN = r"^[A-Za-z0-9_*\-]+(/[A-Za-z0-9_*\-]+)*$"
# A module name as `import` takes it: identifiers joined by dots (`my_lab_tasks`, `lab.tasks`).
MODULE_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$"


class SuiteError(ValueError):
    """A suite file is missing, unreadable or invalid; the message says where and why."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class VerificationThresholds(_Strict):
    """What `manieval challenge verify` asks of every task before the suite opens
    (docs/verification.md): the organizer's reference solves it, a random policy does not."""

    reference_min_success: float = Field(default=0.5, ge=0, le=1)
    """The least success rate of the reference solution on each task, on the dev seeds."""
    random_max_success: float = Field(default=0.2, gt=0, le=1)
    """The random policy's success rate on each task stays under this: the task is not
    trivial."""


class TaskThresholds(_Strict):
    """One task's own thresholds, over the suite's `verification` where given."""

    reference_min_success: float | None = Field(default=None, ge=0, le=1)
    random_max_success: float | None = Field(default=None, gt=0, le=1)


class TaskConfig(_Strict):
    """One ManiSkill task as the suite runs it."""

    env_id: str = Field(pattern=r"^[A-Za-z0-9_\-]+-v\d+$")
    obs_mode: str = Field(default="state_dict", pattern=OBS_MODE_PATTERN)
    control_mode: str = "pd_ee_delta_pose"
    sim_backend: Literal["physx_cpu", "physx_cuda"] = "physx_cpu"
    episodes: int = Field(default=50, ge=1, le=10_000)
    max_episode_steps: int = Field(ge=1, le=100_000)
    instruction: str = Field(default="", max_length=1000)
    """What the task asks, in words, for policies that take a language instruction; it reaches
    the policy in the task spec. Empty: none (and not part of the hash)."""
    verification: TaskThresholds = TaskThresholds()
    """This task's verification thresholds where they differ from the suite's (a task the
    reference does not solve yet: `reference_min_success: 0`, which the report then shows).
    Not in the hash, as the suite's."""


class PublicSeeds(_Strict):
    """Seeds anyone can reproduce: `start`, `start + 1`, ... for every task."""

    kind: Literal["public"] = "public"
    start: int = Field(default=0, ge=0, lt=SEED_LIMIT)


class SecretSeeds(_Strict):
    """Seeds derived from a server secret by HMAC-SHA256, unknowable to participants."""

    kind: Literal["secret"] = "secret"


class Phase(_Strict):
    """A phase of the benchmark (e.g. `dev`, `test`) and where its seeds come from."""

    description: str = ""
    seeds: Annotated[PublicSeeds | SecretSeeds, Field(discriminator="kind")]
    significance_level: float = Field(default=0.05, gt=0, le=0.5)
    """The family-wise level at which the phase's board separates neighbours into tie groups
    (McNemar's exact test, Holm's correction: docs/metrics.md, "Paired significance"). How
    results are read, not what is evaluated: not in the hash."""
    counts: Literal["best", "last"] = "best"
    """Which of a participant's submissions stands on the board: the best-scoring or the
    latest (docs/server.md, Challenge rules). The rules below, like the level, are how the
    phase is run, not what is evaluated: not in the hash."""
    final_choice: bool = False
    """A participant may mark one submission as final: it stands on the board, whatever
    `counts` says, once it succeeded."""
    after_close: Literal["refuse", "post_deadline"] = "refuse"
    """What a submission after the phase closes gets: refused, or evaluated for the phase's
    post-deadline board, which never mixes with the official one."""
    board: Literal["public", "hidden"] = "public"
    """A hidden board shows each participant only their own rows until an organizer publishes
    it (`manieval challenge publish`); organizers see it all."""


RULES = ("significance_level", "counts", "final_choice", "after_close", "board")
"""A phase's settings that say how it is run and read, not what is evaluated."""


class Nominal(_Strict):
    kind: Literal["nominal"] = "nominal"


class ObsNoise(_Strict):
    """Gaussian noise on every floating-point observation entry."""

    kind: Literal["obs_noise"] = "obs_noise"
    sigma: float = Field(gt=0, le=10)


class ActionDelay(_Strict):
    """The policy acts on observations `steps` control steps old."""

    kind: Literal["action_delay"] = "action_delay"
    steps: int = Field(ge=1, le=100)


class LowFreq(_Strict):
    """The controller takes actions at `control_freq` Hz instead of the task's default."""

    kind: Literal["low_freq"] = "low_freq"
    control_freq: int = Field(default=5, ge=1, le=100)


class ObsMode(_Strict):
    """The same scenes seen through another observation mode (`pointcloud` instead of `rgbd`)."""

    kind: Literal["obs_mode"] = "obs_mode"
    obs_mode: str = Field(pattern=OBS_MODE_PATTERN)


ConditionParams = Annotated[
    Nominal | ObsNoise | ActionDelay | LowFreq | ObsMode, Field(discriminator="kind")
]


class Condition(_Strict):
    """A named evaluation condition: nominal or a sim-to-real stress."""

    name: str = Field(pattern=r"^[a-z0-9_\-]+$")
    params: ConditionParams


class Limits(_Strict):
    """What a policy may take: per-call timeouts, the whole evaluation's budget, frame size."""

    connect_timeout_s: float = Field(default=120.0, gt=0)
    first_call_timeout_s: float = Field(default=120.0, gt=0)
    call_timeout_s: float = Field(default=10.0, gt=0)
    budget_s: float = Field(default=7200.0, gt=0)
    max_action_frame_bytes: int = Field(default=1 << 20, ge=1024)


class ActionChunks(_Strict):
    """How many actions a policy may answer one `act` with (protocol 2), and how many of them
    the evaluator executes before it asks again. The default, 1, is one action per call."""

    max_length: int = Field(default=1, ge=1, le=1024)
    """The longest chunk the evaluator takes; a longer one fails the episode (invalid_action)."""
    execute: int | None = Field(default=None, ge=1)
    """Actions of each chunk executed before the policy is asked again (None: all of them)."""

    @model_validator(mode="after")
    def _execute_within_max_length(self) -> ActionChunks:
        if self.execute is not None and self.execute > self.max_length:
            raise ValueError(
                f"action_chunks.execute ({self.execute}) exceeds max_length ({self.max_length})"
            )
        return self

    @property
    def executed(self) -> int:
        """The most actions of one chunk that are executed: `execute`, or all a chunk can hold."""
        return self.execute or self.max_length


NO_CHUNKS = ActionChunks()
"""One action per call: protocol 1's way, and every suite's unless it says otherwise."""


class PolicyResources(_Strict):
    """What each policy container is given beyond the service's CPU and memory limits."""

    gpus: int = Field(default=0, ge=0, le=8)
    """GPUs for the policy's container (0: none). A service gives a policy at most its
    operator's `MANIEVAL_POLICY_GPUS` and refuses the suite's submissions if that is fewer."""

    def refusal(self, *, available: int) -> str | None:
        """Why a service that gives a policy at most `available` GPUs cannot run it, or None."""
        if self.gpus <= available:
            return None
        given = f"at most {available}" if available else "none"
        return (
            f"this challenge asks for {self.gpus} GPU{'s' if self.gpus > 1 else ''} per policy, "
            f"and this service has {given} for policies (its operator sets MANIEVAL_POLICY_GPUS)"
        )


class Suite(_Strict):
    """A benchmark: what to run, on which seeds, under which conditions."""

    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_\-]*$")
    version: int = Field(ge=1)
    title: str = Field(default="", max_length=200)
    """How people read the suite's name ("ManiSkill Core"); not part of what is evaluated, so
    not in the hash."""
    description: str = ""
    tasks: tuple[TaskConfig, ...] = Field(min_length=1)
    phases: dict[str, Phase] = Field(min_length=1)
    conditions: tuple[Condition, ...] = (Condition(name="nominal", params=Nominal()),)
    limits: Limits = Limits()
    action_chunks: ActionChunks = NO_CHUNKS
    """Whether a policy may answer with several actions at once (docs/protocol.md, "Action
    chunks"); the default takes one action per call, as protocol 1 does."""
    observation_keys: tuple[Annotated[str, Field(pattern=OBS_KEY_PATTERN)], ...] | None = None
    """The observation entries a policy sees, as paths such as `agent/qpos` or
    `sensor_data/*/rgb` (an entry named by a path comes whole, with everything below it); the
    evaluator drops every other entry before the policy, or its task spec, sees it. None: all
    that the task's obs_mode gives."""
    ignore_terminations: bool = False
    """As ManiSkill's evaluation does: every episode runs to its step limit, whatever the task
    signals, so that both `success_once` and `success_at_end` are measured. False ends an
    episode at its first termination (a success) and reports no `success_at_end`."""
    shards: int = Field(default=1, ge=1, le=64)
    """Pods a submission's episodes are spread over on Kubernetes (an Indexed Job); the other
    executors ignore it. Episodes do not depend on where they ran, so it is not in the hash."""
    videos: int = Field(default=0, ge=0, le=100)
    """The first `videos` episodes of each task under each condition are recorded as videos
    (shown on the submission's page); 0 records none. Recording changes no result, so it is
    not in the hash."""
    video_conditions: tuple[str, ...] | None = None
    """Only these conditions' episodes are recorded (None: every condition's): rendering a
    frame costs several times a step on the CPU. Not in the hash either."""
    video_size: int | None = Field(default=None, ge=64, le=2048, multiple_of=16)
    """Recorded frames are this many pixels a side (None: the task's own render camera, 512 for
    ManiSkill's tabletop tasks); H.264 wants a multiple of 16. Square: for square cameras set
    by field of view, as the tabletop tasks' are. Not in the hash either."""
    video_fps: int | None = Field(default=None, ge=1, le=120)
    """At most this many frames per second of the episode's control time (None: one frame
    after every step): every k-th step is filmed, k the smallest whole number that keeps the
    rate under it, and the last step always. Not in the hash either."""
    packages: tuple[str, ...] = ()
    """Python packages that register the suite's own ManiSkill tasks when imported, in import
    order (docs/task-packages.md): organizer code, imported by the evaluator before it makes
    environments, never by a policy."""
    package_versions: dict[str, str] = {}
    """Each package's version, as `manieval challenge load` records it (or the suite states it:
    loading then checks it): in the hash, so that a changed task is another suite. Empty: not
    pinned yet; otherwise one for every package."""
    policy: PolicyResources = PolicyResources()
    """What the policy's container is given (`policy: {gpus: 1}`). Not in the hash: like the
    service's CPU and memory limits, hardware makes a policy faster or slower, while what it
    is scored on (tasks, seeds, conditions, time limits) stays what the hash names."""
    verification: VerificationThresholds = VerificationThresholds()
    """What `manieval challenge verify` asks of each task (docs/verification.md). How the suite
    is checked before it opens, not what a policy is scored on: not in the hash, and a stored
    report is judged again against the suite's thresholds whenever the suite is loaded."""

    @model_validator(mode="after")
    def _unique_names(self) -> Suite:
        for label, names in (
            ("task", [t.env_id for t in self.tasks]),
            ("condition", [c.name for c in self.conditions]),
        ):
            duplicates = sorted({n for n in names if names.count(n) > 1})
            if duplicates:
                raise ValueError(f"duplicate {label} names: {', '.join(duplicates)}")
        known = [c.name for c in self.conditions]
        unknown = [c for c in self.video_conditions or () if c not in known]
        if unknown:
            raise ValueError(
                f"video_conditions names no condition of the suite: {', '.join(unknown)} "
                f"(it has: {', '.join(known)})"
            )
        return self

    @model_validator(mode="after")
    def _packages_pinned_together(self) -> Suite:
        if len(set(self.packages)) != len(self.packages):
            raise ValueError(f"packages are named twice: {', '.join(self.packages)}")
        invalid = [p for p in self.packages if not is_module_name(p)]
        if invalid:
            raise ValueError(
                f"packages: not a module name as `import` takes it: {', '.join(map(repr, invalid))}"
                " (identifiers joined by dots, such as my_lab_tasks: the import name, which may"
                " differ from the distribution's name on PyPI)"
            )
        if self.package_versions and set(self.package_versions) != set(self.packages):
            raise ValueError(
                "package_versions gives a version for every package and nothing else "
                f"(packages: {', '.join(self.packages) or 'none'}; "
                f"package_versions: {', '.join(self.package_versions)})"
            )
        return self

    @model_validator(mode="after")
    def _keys_select_from_dicts(self) -> Suite:
        if self.observation_keys is None:
            return self
        modes = {t.obs_mode for t in self.tasks}
        modes |= {c.params.obs_mode for c in self.conditions if isinstance(c.params, ObsMode)}
        if FLAT_OBS_MODES & modes:
            raise ValueError(
                f"observation_keys select entries of dict observations; obs_mode "
                f"{', '.join(sorted(FLAT_OBS_MODES & modes))} gives one flat array"
            )
        return self

    def thresholds(self, env_id: str) -> VerificationThresholds:
        """What verification asks of the task `env_id`: its own thresholds over the suite's."""
        own = self.task(env_id).verification.model_dump(exclude_none=True)
        return self.verification.model_copy(update=own)

    def task(self, env_id: str) -> TaskConfig:
        """The task named `env_id`, or SuiteError listing the suite's tasks."""
        for task in self.tasks:
            if task.env_id == env_id:
                return task
        known = ", ".join(t.env_id for t in self.tasks)
        raise SuiteError(f"suite {self.name!r} has no task {env_id!r} (it has: {known})")

    def condition(self, name: str) -> Condition:
        """The condition called `name`, or SuiteError listing the suite's conditions."""
        for condition in self.conditions:
            if condition.name == name:
                return condition
        known = ", ".join(c.name for c in self.conditions)
        raise SuiteError(f"suite {self.name!r} has no condition {name!r} (it has: {known})")

    def phase(self, name: str) -> Phase:
        """The phase called `name`, or SuiteError listing the suite's phases."""
        if name not in self.phases:
            known = ", ".join(self.phases)
            raise SuiteError(f"suite {self.name!r} has no phase {name!r} (it has: {known})")
        return self.phases[name]

    def sha256(self) -> str:
        """Hash of the suite's canonical JSON form: names exactly what was evaluated."""
        content = self.model_dump(
            mode="json", exclude={"shards", "title", "policy", "verification", *RECORDING}
        )
        for phase in content["phases"].values():
            for name in RULES:
                del phase[name]
        for name in _HASHED_WHEN_SET:  # suites that do not use a newer setting keep their hash
            if getattr(self, name) == type(self).model_fields[name].default:
                del content[name]
        for task in content["tasks"]:
            del task["verification"]
            for name in _TASK_HASHED_WHEN_SET:
                if task[name] == TaskConfig.model_fields[name].default:
                    del task[name]
        canonical = json.dumps(content, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()


# Settings added after suites were first published: part of the hash only when not the default.
_HASHED_WHEN_SET = (
    "ignore_terminations",
    "action_chunks",
    "observation_keys",
    "packages",
    "package_versions",
)
_TASK_HASHED_WHEN_SET = ("instruction",)
RECORDING = ("videos", "video_conditions", "video_size", "video_fps")
"""The settings that say what is filmed and how: they change no result, so no hash."""


def is_module_name(name: str) -> bool:
    """Whether `import name` could import it: identifiers joined by dots, none a keyword."""
    return re.fullmatch(MODULE_PATTERN, name) is not None and not any(
        iskeyword(part) for part in name.split(".")
    )


def suite_path(ref: str | Path) -> Path:
    """The file of a suite named by file path, or by name from the bundled `suites/` directory."""
    path = Path(ref)
    if not path.suffix and not path.exists():
        path = SUITES_DIR / f"{ref}.yaml"
    return path


def load_suite(ref: str | Path) -> Suite:
    """Load a suite by file path, or by name from the bundled `suites/` directory."""
    path = suite_path(ref)
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        bundled = ", ".join(sorted(p.stem for p in SUITES_DIR.glob("*.yaml")))
        raise SuiteError(f"no suite file {path} (bundled suites: {bundled})") from None
    except yaml.YAMLError as exc:
        raise SuiteError(f"{path}: not valid YAML: {exc}") from None
    try:
        return Suite.model_validate(raw)
    except ValidationError as exc:
        raise SuiteError(f"{path}: invalid suite:\n{exc}") from None


def phase_seeds(
    suite: Suite, phase_name: str, env_id: str, count: int, *, secret: bytes | None = None
) -> list[int]:
    """The concrete seeds of `count` episodes of one task in one phase."""
    seeds = suite.phase(phase_name).seeds
    if isinstance(seeds, PublicSeeds):
        if seeds.start + count > SEED_LIMIT:
            raise SuiteError(
                f"phase {phase_name!r}: {count} seeds from {seeds.start} overflow int32"
            )
        return [seeds.start + i for i in range(count)]
    if not secret:
        raise SuiteError(f"phase {phase_name!r} has secret seeds: a seed secret is required")
    return [_secret_seed(secret, suite.name, phase_name, env_id, i) for i in range(count)]


def _secret_seed(secret: bytes, suite: str, phase: str, env_id: str, index: int) -> int:
    message = f"{suite}/{phase}/{env_id}/{index}".encode()
    digest = hmac.new(secret, message, hashlib.sha256).digest()
    return int.from_bytes(digest[:8], "big") % SEED_LIMIT


def seed_commitment(seeds_by_task: dict[str, list[int]], *, salt: str) -> str:
    """SHA-256 commitment to a phase's seeds, publishable before the seeds are revealed."""
    body = json.dumps({"salt": salt, "seeds": seeds_by_task}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(body.encode()).hexdigest()
