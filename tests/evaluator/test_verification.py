"""Verification before opening (evaluator/verification.py): how a report is judged against a
suite, and the bundled suites' own reports. `manieval challenge verify` itself, on real
ManiSkill tasks: tests/server/test_cli_verify.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from evaluator import packages
from evaluator.suite import SUITES_DIR, Suite, SuiteError, VerificationThresholds, load_suite
from evaluator.verification import (
    problems,
    read_report,
    report_path,
    verification_phase,
)
from testkit.factories import SUITE
from testkit.verification import task_line, verification_report


def suite_of(*env_ids: str, **fields: object) -> Suite:
    """The test suite with these tasks (PickCube-v1 only, by default) and other fields."""
    raw = yaml.safe_load(SUITE.read_text())
    if env_ids:
        raw["tasks"] = [{"env_id": e, "max_episode_steps": 100} for e in env_ids]
    return Suite.model_validate({**raw, **fields})


def test_a_report_whose_tasks_meet_the_thresholds_passes() -> None:
    suite = suite_of()
    assert problems(verification_report(suite), suite, path=Path("r.json")) == []


def test_each_failure_names_its_task_and_says_which_rule_it_breaks() -> None:
    suite = suite_of("PickCube-v1", "Unsolved-v1", "Trivial-v1", "Flaky-v1")
    report = verification_report(
        suite,
        task_line(suite, "PickCube-v1"),
        task_line(suite, "Unsolved-v1", reference_successes=1),
        task_line(suite, "Trivial-v1", random_successes=5),
        task_line(suite, "Flaky-v1", differing_episodes=(2, 7)),
    )
    assert report.failures == [
        "Unsolved-v1: the reference solved 1 of 10 episodes (10%), under the suite's "
        "reference_min_success (50%)",
        "Trivial-v1: the random policy solved 5 of 10 episodes (50%), not under the suite's "
        "random_max_success (20%): the task is trivial",
        "Flaky-v1: the reference's episodes 2, 7 differ between 1 and 2 workers: the task is "
        "not deterministic, or its episodes not independent",
    ]
    assert not report.passed


def test_a_run_that_stopped_early_fails_the_report() -> None:
    suite = suite_of()
    report = verification_report(suite, aborted=("random policy: the policy crashed",))
    assert report.failures == ["a run stopped early: random policy: the policy crashed"]


def test_a_report_is_judged_again_against_the_suites_thresholds_of_now() -> None:
    suite = suite_of()
    report = verification_report(suite)  # 9 of 10: passes the default 50%
    stricter = suite_of(verification={"reference_min_success": 0.95})
    assert stricter.sha256() == suite.sha256()  # thresholds are not in the hash
    found = problems(report, stricter, path=Path("r.json"))
    assert found == [
        "PickCube-v1: the reference solved 9 of 10 episodes (90%), under the suite's "
        "reference_min_success (95%)"
    ]


def test_a_tasks_own_thresholds_override_the_suites_and_stay_out_of_the_hash() -> None:
    plain = suite_of("PickCube-v1", "PegInsertionSide-v1")
    raw = plain.model_dump()
    raw["tasks"][1]["verification"] = {"reference_min_success": 0}
    lenient = Suite.model_validate(raw)
    assert lenient.sha256() == plain.sha256()
    assert lenient.thresholds("PegInsertionSide-v1") == VerificationThresholds(
        reference_min_success=0, random_max_success=0.2
    )
    for suite in (plain, lenient):
        lines = [task_line(suite, "PickCube-v1")]
        lines.append(task_line(suite, "PegInsertionSide-v1", reference_successes=0))
        assert verification_report(suite, *lines).passed is (suite is lenient)


def test_a_report_of_another_suite_or_none_at_all_verifies_nothing() -> None:
    suite = suite_of()
    changed = suite_of(version=suite.version + 1)
    stale = problems(verification_report(suite), changed, path=Path("s.verification.json"))
    assert len(stale) == 1
    assert "is of another suite" in stale[0]
    assert "verify it again" in stale[0]
    missing = problems(None, suite, path=Path("s.verification.json"))
    assert missing == [
        "no verification report beside the suite (s.verification.json): "
        "run `manieval challenge verify`"
    ]


def test_the_report_lives_beside_the_suite_file(tmp_path: Path) -> None:
    assert report_path("maniskill-core") == SUITES_DIR / "maniskill-core.verification.json"
    assert report_path(tmp_path / "lab.yaml") == tmp_path / "lab.verification.json"
    assert read_report(tmp_path / "lab.verification.json") is None
    (tmp_path / "lab.verification.json").write_text("{}")
    with pytest.raises(SuiteError, match="not a verification report"):
        read_report(tmp_path / "lab.verification.json")


def test_verification_runs_on_the_dev_seeds_or_else_the_first_public_ones() -> None:
    suite = suite_of()
    assert verification_phase(suite) == "dev"
    secret_only = suite.model_copy(update={"phases": {"test": suite.phases["test"]}})
    with pytest.raises(SuiteError, match="no phase with public seeds"):
        verification_phase(secret_only)


@pytest.mark.parametrize("name", ["maniskill-core", "maniskill-visual"])
def test_each_bundled_suite_ships_a_report_that_verifies_it(name: str) -> None:
    """Editing a bundled suite in what its hash names needs `manieval challenge verify` again
    (docs/verification.md, the command that made each report)."""
    suite, _ = packages.pin(load_suite(name))
    report = read_report(report_path(name))
    assert problems(report, suite, path=report_path(name)) == []
    assert report is not None
    assert report.reference == "local:scripted"
    assert [t.env_id for t in report.tasks] == [t.env_id for t in suite.tasks]
