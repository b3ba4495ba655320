"""Verification before a suite opens (docs/verification.md): the organizer's reference solution
solves every task, the random policy does not, the episodes come out the same with 1 and 2
workers; with each task's step headroom and evaluation cost. The report lives beside the suite
file and names the suite's hash; it is judged again against the suite's thresholds on loading."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from evaluator.bundled import LOCAL_PREFIX, bundled_policies
from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import (
    EvaluationResult,
    SuiteRef,
    TaskResult,
    Versions,
    episode_records,
)
from evaluator.sources import LocalDirectory
from evaluator.suite import PublicSeeds, Suite, SuiteError, VerificationThresholds, suite_path

REPORT_SUFFIX = ".verification.json"
RANDOM_POLICY = "random"
WORKERS = (1, 2)  # the reference runs with each; their records must be equal


class _Doc(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TaskVerification(_Doc):
    """What verification measured on one task, under the suite's first condition."""

    env_id: str
    episodes: int = Field(ge=1)
    max_episode_steps: int = Field(ge=1)
    reference_successes: int = Field(ge=0)
    random_successes: int = Field(ge=0)
    reference_steps_max: int | None = Field(
        description="The most steps a successful episode of the reference needed (null: none "
        "succeeded); against max_episode_steps, the task's step headroom"
    )
    seconds_per_episode: float = Field(
        ge=0, description="Mean wall time of the reference's episodes on one worker"
    )
    differing_episodes: list[int] = Field(
        description="Episodes whose records differ between 1 and 2 workers (empty: none)"
    )
    thresholds: VerificationThresholds = Field(description="The task's, as the report was made")

    @property
    def reference_rate(self) -> float:
        return self.reference_successes / self.episodes

    @property
    def random_rate(self) -> float:
        return self.random_successes / self.episodes

    @property
    def headroom(self) -> float | None:
        """The step limit over the steps the reference needed (2.0: twice what it needed)."""
        steps = self.reference_steps_max
        return self.max_episode_steps / steps if steps else None


class VerificationReport(_Doc):
    """The report of `manieval challenge verify`, stored as SUITE.verification.json."""

    schema_version: Literal["1"] = "1"
    suite: SuiteRef
    phase: str
    condition: str
    reference: str
    random: str
    versions: Versions
    created_at: datetime
    thresholds: VerificationThresholds = Field(
        description="The suite's, as the report was made; a task's own are in its line"
    )
    aborted: list[str] = Field(description="Runs that stopped before their last episode, why")
    tasks: list[TaskVerification]
    failures: list[str] = Field(description="Why it failed against `thresholds` (empty: passed)")

    @property
    def passed(self) -> bool:
        return not self.failures


def report_path(suite_ref: str | Path) -> Path:
    """Where a suite's verification report lives: beside its file, `NAME.verification.json`."""
    path = suite_path(suite_ref)
    return path.with_name(path.stem + REPORT_SUFFIX)


def read_report(path: Path) -> VerificationReport | None:
    """The report stored at `path`, or None where there is none; SuiteError if unreadable."""
    try:
        return VerificationReport.model_validate_json(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValidationError) as exc:
        raise SuiteError(f"{path}: not a verification report: {exc}") from None


def failures(report: VerificationReport, suite: Suite) -> list[str]:
    """Why the report fails the suite's thresholds, a line per task and problem, each naming
    its task (the suite's tasks are the report's: `problems` checks the hash first)."""
    found = [f"a run stopped early: {reason}" for reason in report.aborted]
    for task in report.tasks:
        thresholds = suite.thresholds(task.env_id)
        if task.reference_rate < thresholds.reference_min_success:
            found.append(
                f"{task.env_id}: the reference solved {task.reference_successes} of "
                f"{task.episodes} episodes ({task.reference_rate:.0%}), under the suite's "
                f"reference_min_success ({thresholds.reference_min_success:.0%})"
            )
        if task.random_rate >= thresholds.random_max_success:
            found.append(
                f"{task.env_id}: the random policy solved {task.random_successes} of "
                f"{task.episodes} episodes ({task.random_rate:.0%}), not under the suite's "
                f"random_max_success ({thresholds.random_max_success:.0%}): the task is trivial"
            )
        if task.differing_episodes:
            shown = ", ".join(map(str, task.differing_episodes))
            found.append(
                f"{task.env_id}: the reference's episodes {shown} differ between 1 and 2 "
                "workers: the task is not deterministic, or its episodes not independent"
            )
    return found


def problems(report: VerificationReport | None, suite: Suite, *, path: Path) -> list[str]:
    """Why `suite` (as loaded, its packages pinned) is not verified by the report at `path`:
    none there, made for another suite, or failing the suite's thresholds now (empty: none)."""
    if report is None:
        return [f"no verification report at {path}: run `manieval challenge verify`"]
    sha256 = suite.sha256()
    if report.suite.sha256 != sha256:
        return [
            f"the verification report at {path} is of another suite (sha256 "
            f"{report.suite.sha256[:12]}, this one's is {sha256[:12]}): verify it again"
        ]
    return failures(report, suite)


def verification_phase(suite: Suite) -> str:
    """The phase whose seeds verification runs on: `dev`, else the first with public seeds."""
    public = [n for n, p in suite.phases.items() if isinstance(p.seeds, PublicSeeds)]
    if not public:
        raise SuiteError(f"suite {suite.name!r} has no phase with public seeds to verify on")
    return "dev" if "dev" in public else public[0]


def verification_plan(suite: Suite, *, episodes: int | None) -> EvaluationPlan:
    """Every task under the suite's first condition, on the dev seeds, nothing filmed."""
    return build_plan(
        suite,
        verification_phase(suite),
        conditions=[suite.conditions[0].name],
        episodes=episodes,
        videos=0,
    )


def policy_label(directory: Path) -> str:
    """How the report names a policy: `local:NAME` for a bundled one (the same on every
    machine), else its directory."""
    bundled = {path.resolve(): name for name, path in bundled_policies().items()}
    name = bundled.get(directory.resolve())
    return f"{LOCAL_PREFIX}{name}" if name else f"dir:{directory.resolve()}"


def reference_policy(reference: str) -> Path:
    """The reference's policy directory: `reference` itself, or the bundled policy of that
    name; ValueError naming both where neither holds a `policy.py`."""
    policy = Path(reference)
    if not policy.is_dir():
        policy = bundled_policies().get(reference, policy)
    if not (policy / "policy.py").is_file():
        known = ", ".join(bundled_policies())
        raise ValueError(
            f"--reference {reference}: no policy.py there, and no bundled policy of that name "
            f"(bundled: {known})"
        )
    return policy


def random_policy() -> Path:
    """The bundled random policy's directory."""
    return bundled_policies()[RANDOM_POLICY]


def verify(
    suite: Suite,
    reference: Path,
    *,
    episodes: int | None = None,
    on_run: Callable[[str, EvaluationPlan], None] = lambda _name, _plan: None,
    now: Callable[[], datetime] = lambda: datetime.now(UTC),
) -> VerificationReport:
    """Run the reference on 1 worker, the random policy, the reference on 2 workers, on the
    dev seeds, and judge them against the suite's thresholds. `suite` is as loaded (its
    packages pinned); `reference` is a policy directory; `on_run` hears of each run as it
    starts."""
    plan = verification_plan(suite, episodes=episodes)
    reference_source = LocalDirectory(reference)
    chance_source = LocalDirectory(random_policy())
    runs: list[tuple[str, EvaluationResult]] = []
    for name, source, workers in (
        ("reference, 1 worker", reference_source, WORKERS[0]),
        ("random policy", chance_source, 1),
        ("reference, 2 workers", reference_source, WORKERS[1]),
    ):
        on_run(name, plan)
        runs.append((name, evaluate(plan, source, workers=workers)))
    (_, one), (_, chance), (_, two) = runs
    report = VerificationReport(
        suite=plan.suite,
        phase=plan.phase,
        condition=plan.runs[0].condition.name,
        reference=policy_label(reference),
        random=policy_label(random_policy()),
        versions=one.versions,
        created_at=now(),
        thresholds=suite.verification,
        aborted=[f"{name}: {r.abort.reason}" for name, r in runs if r.abort is not None],
        tasks=[
            measured(
                suite.thresholds(run.env_id),
                run.max_episode_steps,
                task,
                chance_task,
                differing(one, two, run.env_id),
            )
            for run, task, chance_task in zip(
                plan.runs, one.conditions[0].tasks, chance.conditions[0].tasks, strict=True
            )
        ],
        failures=[],
    )
    report.failures = failures(report, suite)
    return report


def measured(
    thresholds: VerificationThresholds,
    max_episode_steps: int,
    reference: TaskResult,
    chance: TaskResult,
    differing: list[int],
) -> TaskVerification:
    """One task's line of the report, from the reference's and the random policy's results."""
    solved = [e.steps for e in reference.episodes if e.success_once]
    return TaskVerification(
        env_id=reference.env_id,
        episodes=reference.episodes_planned,
        max_episode_steps=max_episode_steps,
        reference_successes=reference.successes,
        random_successes=chance.successes,
        reference_steps_max=max(solved) if solved else None,
        seconds_per_episode=sum(e.wall_time_s for e in reference.episodes)
        / max(len(reference.episodes), 1),
        differing_episodes=differing,
        thresholds=thresholds,
    )


def differing(one: EvaluationResult, two: EvaluationResult, env_id: str) -> list[int]:
    """The indexes of a task's episodes whose records differ between two results."""
    first, second = ([r for r in episode_records(r) if r["task"] == env_id] for r in (one, two))
    if len(first) != len(second):
        return list(range(max(len(first), len(second))))
    return [i for i, (a, b) in enumerate(zip(first, second, strict=True)) if a != b]
