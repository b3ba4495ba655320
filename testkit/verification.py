"""Verification reports for tests (evaluator/verification.py): made up, as `manieval challenge
verify` would write them, without running a single episode."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from evaluator import packages
from evaluator.results import SuiteRef, Versions
from evaluator.suite import Suite, load_suite
from evaluator.verification import (
    TaskVerification,
    VerificationReport,
    failures,
    report_path,
)

VERSIONS = Versions(manieval="0", mani_skill="3.0.1", sapien="3.0.3", torch="2", python="3.11")


def task_line(
    suite: Suite,
    env_id: str,
    *,
    episodes: int = 10,
    reference_successes: int = 9,
    random_successes: int = 0,
    differing_episodes: tuple[int, ...] = (),
) -> TaskVerification:
    """One task's line: by default solved by the reference 9 times in 10, never by chance."""
    return TaskVerification(
        env_id=env_id,
        episodes=episodes,
        max_episode_steps=suite.task(env_id).max_episode_steps,
        reference_successes=reference_successes,
        random_successes=random_successes,
        reference_steps_max=suite.task(env_id).max_episode_steps // 2
        if reference_successes
        else None,
        seconds_per_episode=1.5,
        differing_episodes=list(differing_episodes),
        thresholds=suite.thresholds(env_id),
    )


def verification_report(
    suite: Suite, *lines: TaskVerification, aborted: tuple[str, ...] = ()
) -> VerificationReport:
    """A report of `suite` with these task lines (default: each task passing)."""
    report = VerificationReport(
        suite=SuiteRef(name=suite.name, version=suite.version, sha256=suite.sha256()),
        phase="dev",
        condition=suite.conditions[0].name,
        reference="local:scripted",
        random="local:random",
        versions=VERSIONS,
        created_at=datetime(2026, 11, 27, tzinfo=UTC),
        thresholds=suite.verification,
        aborted=list(aborted),
        tasks=list(lines) or [task_line(suite, t.env_id) for t in suite.tasks],
        failures=[],
    )
    report.failures = failures(report, suite)
    return report


def write_report(suite_file: Path, **task_fields: object) -> Path:
    """Write beside `suite_file` a report of it whose every task has `task_fields` (default:
    passing); the report's path."""
    suite, _ = packages.pin(load_suite(suite_file))
    lines = [task_line(suite, t.env_id, **task_fields) for t in suite.tasks]  # type: ignore[arg-type]
    path = report_path(suite_file)
    path.write_text(verification_report(suite, *lines).model_dump_json(indent=2))
    return path


def suite_copy(directory: Path, source: Path) -> Path:
    """A copy of the suite file `source` in `directory`, where a report can be written."""
    copy = directory / source.name
    copy.write_text(source.read_text())
    return copy
