"""The report of verification before a suite opens (docs/verification.md), where it lives and
how it is judged: the report lives beside the suite file and names the suite's hash; it is
judged again against the suite's thresholds whenever the suite is loaded. Running it:
`evaluator/verify.py` (the server reads reports without importing the evaluation machinery)."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from evaluator.results import SuiteRef, Versions
from evaluator.suite import PublicSeeds, Suite, SuiteError, VerificationThresholds, suite_path

REPORT_SUFFIX = ".verification.json"


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
        # Names only: the problems are shown on the challenge's public page.
        return [
            f"no verification report beside the suite ({path.name}): "
            "run `manieval challenge verify`"
        ]
    sha256 = suite.sha256()
    if report.suite.sha256 != sha256:
        return [
            f"the verification report {path.name} is of another suite (sha256 "
            f"{report.suite.sha256[:12]}, this one's is {sha256[:12]}): verify it again"
        ]
    return failures(report, suite)


def verification_phase(suite: Suite) -> str:
    """The phase whose seeds verification runs on: `dev`, else the first with public seeds."""
    public = [n for n, p in suite.phases.items() if isinstance(p.seeds, PublicSeeds)]
    if not public:
        raise SuiteError(f"suite {suite.name!r} has no phase with public seeds to verify on")
    return "dev" if "dev" in public else public[0]
