"""A challenge's verification (docs/verification.md): the report beside its suite file, judged
against the suite's thresholds when the suite is loaded, kept with the challenge for its page."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.table import Table

from evaluator.suite import Suite
from evaluator.verification import VerificationReport, problems, read_report, report_path
from server.kit.errors import Conflict


class Unverified(Conflict):
    """The suite has no passing verification report, and was not loaded as unverified."""

    code = "unverified"

    def __init__(self, suite: str, found: list[str]) -> None:
        lines = "\n".join(f"  {problem}" for problem in found)
        super().__init__(f"suite {suite!r} is not verified:\n{lines}")
        self.problems = found


@dataclass(frozen=True)
class Verification:
    """A suite's report (None: none found) and why it does not verify the suite (empty: it
    does)."""

    report: VerificationReport | None
    problems: list[str]

    @property
    def passed(self) -> bool:
        return self.report is not None and not self.problems

    def stored(self) -> dict[str, Any]:
        """As `Challenge.verification` keeps it."""
        report = None if self.report is None else self.report.model_dump(mode="json")
        return {"report": report, "problems": self.problems}


def suite_verification(suite_ref: str | Path, suite: Suite) -> Verification:
    """The verification of `suite` (as loaded, packages pinned) by the report beside its file."""
    path = report_path(suite_ref)
    report = read_report(path)  # SuiteError: a report there that is not one
    return Verification(report=report, problems=problems(report, suite, path=path))


def stored_verification(stored: dict[str, Any] | None) -> Verification | None:
    """A challenge's verification as loaded (None: loaded before verification was kept)."""
    if stored is None:
        return None
    report = stored.get("report")
    return Verification(
        report=None if report is None else VerificationReport.model_validate(report),
        problems=list(stored.get("problems", [])),
    )


def report_table(report: VerificationReport) -> Table:
    """The report as the terminal shows it: a row per task."""
    table = Table(
        title=f"{report.suite.name} v{report.suite.version}: {report.phase} seeds, condition "
        f"{report.condition}, reference {report.reference}",
        title_justify="left",
    )
    for name in ("task", "reference (needs)", "random (under)", "steps needed", "headroom"):
        table.add_column(name, justify="left" if name == "task" else "right")
    table.add_column("s/episode", justify="right")
    table.add_column("1 vs 2 workers")
    for task in report.tasks:
        table.add_row(
            task.env_id,
            f"{task.reference_successes}/{task.episodes} "
            f"(>={task.thresholds.reference_min_success:.0%})",
            f"{task.random_successes}/{task.episodes} ({task.thresholds.random_max_success:.0%})",
            f"{task.reference_steps_max or '-'} of {task.max_episode_steps}",
            "-" if task.headroom is None else f"{task.headroom:.1f}x",
            f"{task.seconds_per_episode:.2f}",
            "identical" if not task.differing_episodes else "DIFFER",
        )
    return table
