"""Operator commands against a real (SQLite) data directory."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from sqlalchemy import select
from sqlalchemy.orm import selectinload
from typer.testing import CliRunner

from evaluator import packages
from evaluator.suite import load_suite
from evaluator.verification import report_path
from manieval.cli import app
from server.challenges.service import suite_of, with_package_versions
from server.kit.db import make_engine, session_factory
from server.models import Challenge, User
from testkit.factories import PASSWORD, SUITE, gpu_suite
from testkit.verification import suite_copy, write_report

runner = CliRunner()
PACKAGED_SUITE = Path(__file__).resolve().parents[1] / "data" / "task_packages" / "suite.yaml"


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    return tmp_path


def db_session(data: Path):  # type: ignore[no-untyped-def]
    return session_factory(make_engine(f"sqlite:///{data / 'manieval.db'}"))()


def test_admin_create_and_promote(env: Path) -> None:
    r = runner.invoke(
        app,
        ["admin", "create", "chief", "chief@example.org", "--password-stdin"],
        input=PASSWORD + "\n",
    )
    assert r.exit_code == 0, r.output
    with db_session(env) as db:
        user = db.scalar(select(User).where(User.username == "chief"))
        assert user is not None
        assert user.is_admin
    weak = runner.invoke(
        app, ["admin", "create", "other", "o@example.org", "--password-stdin"], input="123\n"
    )
    assert weak.exit_code == 1
    assert "password" in weak.output


def test_challenge_load_creates_then_updates(env: Path) -> None:
    r = runner.invoke(
        app,
        [
            "challenge",
            "load",
            "--unverified",
            str(SUITE),
            "--quota-per-day",
            "3",
            "--closes",
            "test=2030-01-01",
        ],
    )
    assert r.exit_code == 0, r.output
    assert "seed commitment" in r.output
    r = runner.invoke(
        app,
        [
            "challenge",
            "load",
            "--unverified",
            str(SUITE),
            "--quota-per-day",
            "7",
            "--episodes",
            "4",
        ],
    )
    assert r.exit_code == 0, r.output
    with db_session(env) as db:
        challenges = db.scalars(select(Challenge).options(selectinload(Challenge.phases))).all()
        assert len(challenges) == 1
        assert challenges[0].quota_per_day == 7
        assert "episodes: 4" in challenges[0].suite_yaml
        closes = {p.name: p.closes_at for p in challenges[0].phases}
        assert closes["test"] is not None
        assert closes["test"].year == 2030


def test_challenge_load_warns_when_this_service_cannot_give_its_policies_gpus(
    env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    suite = str(gpu_suite(env))
    r = runner.invoke(app, ["challenge", "load", "--unverified", suite])
    assert r.exit_code == 0, r.output  # loaded all the same: the GPUs may come later
    assert "warning: server-gpu refuses submissions until this service has the GPUs" in r.output
    assert "MANIEVAL_POLICY_GPUS" in r.output
    monkeypatch.setenv("MANIEVAL_POLICY_GPUS", "1")
    r = runner.invoke(app, ["challenge", "load", "--unverified", suite])
    assert r.exit_code == 0, r.output
    assert "refuses submissions" not in r.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["challenge", "load", "--unverified", "no-such-suite"], "no suite file"),
        (
            ["challenge", "load", "--unverified", str(SUITE), "--closes", "final=2030-01-01"],
            "no phase",
        ),
        (["challenge", "load", "--unverified", str(SUITE), "--opens", "dev"], "PHASE=ISO-DATE"),
    ],
)
def test_challenge_load_errors(env: Path, args: list[str], message: str) -> None:
    r = runner.invoke(app, args)
    assert r.exit_code in (1, 2)
    assert message in r.output


def test_challenge_load_says_which_task_package_is_missing_and_how_to_install_it(
    env: Path,
) -> None:
    # Another name than the test package's: an earlier test of this process may have imported it.
    suite = env / "missing.yaml"
    suite.write_text(PACKAGED_SUITE.read_text().replace("manieval_test_tasks", "lab_tasks_nowhere"))
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(suite)])
    assert r.exit_code == 1
    assert "task package 'lab_tasks_nowhere' is not installed" in r.output
    assert "-m pip install" in r.output


def test_a_control_plane_without_maniskill_loads_a_suite_that_states_its_versions(
    env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(packages, "simulator_installed", lambda: False)
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(PACKAGED_SUITE)])
    assert r.exit_code == 1
    assert "manieval challenge packages SUITE" in r.output
    stated = env / "stated.yaml"
    text = PACKAGED_SUITE.read_text() + 'package_versions: {manieval_test_tasks: "0.1.0"}\n'
    stated.write_text(text)
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(stated)])
    assert r.exit_code == 0, r.output
    assert "package manieval_test_tasks 0.1.0" in r.output
    with db_session(env) as db:
        challenge = db.scalars(select(Challenge)).one()
        assert challenge.suite_yaml == text
        assert suite_of(challenge).sha256() == challenge.suite_hash


@pytest.mark.sim
def test_challenge_load_pins_task_packages_and_names_each_tasks_provider(
    env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.syspath_prepend(str(PACKAGED_SUITE.parent))
    version = packages.installed_version("manieval_test_tasks")
    r = runner.invoke(app, ["challenge", "packages", str(PACKAGED_SUITE)])
    assert r.exit_code == 0, r.output
    assert f'package_versions: {{"manieval_test_tasks": "{version}"}}' in r.stdout
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(PACKAGED_SUITE)])
    assert r.exit_code == 0, r.output
    assert f"package manieval_test_tasks {version}" in r.output
    assert "task KeepCubeInRing-v1: manieval_test_tasks" in r.output
    with db_session(env) as db:
        challenge = db.scalars(select(Challenge)).one()
        assert challenge.suite_yaml.startswith(PACKAGED_SUITE.read_text())  # comments kept
        suite = suite_of(challenge)
        assert suite.package_versions == {"manieval_test_tasks": version}
        assert suite.sha256() == challenge.suite_hash != load_suite(PACKAGED_SUITE).sha256()


def test_versions_replace_an_empty_package_versions_of_the_text() -> None:
    text = "name: x\npackages: [lab]\npackage_versions: {}\n"
    pinned = yaml.safe_load(with_package_versions(text, {"lab": "1.0"}))
    assert pinned == {"name": "x", "packages": ["lab"], "package_versions": {"lab": "1.0"}}


def test_production_settings_error_is_clear(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("MANIEVAL_DEV_MODE", raising=False)
    monkeypatch.delenv("MANIEVAL_SECRET_KEY", raising=False)
    r = runner.invoke(app, ["db", "upgrade"])
    assert r.exit_code == 2
    assert "MANIEVAL_SECRET_KEY" in r.output


def loaded_with_an_entry(env: Path) -> int:
    """server-tiny loaded by the CLI, its dev board holding one succeeded submission."""
    from server.models import Phase
    from testkit.factories import make_user
    from tests.web.helpers import finished

    assert runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)]).exit_code == 0
    with db_session(env) as db:
        challenge = db.scalar(select(Challenge).options(selectinload(Challenge.phases)))
        assert challenge is not None
        done = finished(db, make_user(db, "alice"), challenge, [True, False])
        assert db.scalar(select(Phase.board_version).where(Phase.id == done.phase_id)) == 1
        return done.id


def test_challenge_reevaluate_queues_every_entry_into_the_next_board_version(env: Path) -> None:
    from server.models import Phase, Submission

    original = loaded_with_an_entry(env)
    r = runner.invoke(app, ["challenge", "reevaluate", "server-tiny", "--phase", "dev"])
    assert r.exit_code == 0, r.output
    assert "phase dev: 1 entries queued for board version 2" in r.output
    with db_session(env) as db:
        copy = db.scalar(select(Submission).where(Submission.reevaluation_of == original))
        assert copy is not None
        assert copy.board_version == 2
        pending = db.scalar(select(Phase.pending_board_version).where(Phase.name == "dev"))
        assert pending == 2
    again = runner.invoke(app, ["challenge", "reevaluate", "server-tiny"])
    assert again.exit_code == 1
    assert "being re-evaluated already (into board version 2)" in again.output


def test_challenge_reevaluate_of_every_phase_skips_those_without_entries(env: Path) -> None:
    loaded_with_an_entry(env)
    r = runner.invoke(app, ["challenge", "reevaluate", "server-tiny"])
    assert r.exit_code == 0, r.output
    assert "phase dev: 1 entries queued for board version 2" in r.output
    assert "phase test: no entries, nothing to re-evaluate" in r.output


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["challenge", "reevaluate"], 2, "Usage: manieval challenge reevaluate"),
        (["challenge", "reevaluate", "server-tiny", "--phase"], 2, "requires an argument"),
        (["challenge", "reevaluate", "no-such"], 1, "no challenge 'no-such'"),
        (["challenge", "reevaluate", "server-tiny", "--phase", "final"], 1, "has no phase"),
        (["challenge", "reevaluate", "server-tiny", "--phase", "test"], 1, "no entries"),
    ],
)
def test_challenge_reevaluate_errors(env: Path, args: list[str], code: int, message: str) -> None:
    assert runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)]).exit_code == 0
    r = runner.invoke(app, args)
    assert r.exit_code == code, r.output
    assert message in r.output


def test_challenge_load_refuses_an_unverified_suite_unless_told_unverified(env: Path) -> None:
    r = runner.invoke(app, ["challenge", "load", str(SUITE)])
    assert r.exit_code == 1, r.output
    assert "suite 'server-tiny' is not verified" in r.output
    assert f"no verification report beside the suite ({report_path(SUITE).name})" in r.output
    assert "or load it with --unverified" in r.output
    with db_session(env) as db:
        assert db.scalar(select(Challenge)) is None
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)])
    assert r.exit_code == 0, r.output
    assert "warning: server-tiny is unverified" in r.output
    with db_session(env) as db:
        challenge = db.scalar(select(Challenge))
        assert challenge is not None
        assert challenge.verification is not None
        assert challenge.verification["report"] is None
        assert challenge.verification["problems"][0].startswith("no verification report")


def test_challenge_load_takes_a_verified_suite_and_keeps_its_report(env: Path) -> None:
    suite = suite_copy(env, SUITE)
    write_report(suite)
    r = runner.invoke(app, ["challenge", "load", str(suite)])
    assert r.exit_code == 0, r.output
    assert "unverified" not in r.output
    assert "verified by local:scripted: 10 episodes a task on the dev seeds, 2026-11-27" in r.output
    with db_session(env) as db:
        challenge = db.scalar(select(Challenge))
        assert challenge is not None
        assert challenge.verification is not None
        assert challenge.verification["problems"] == []
        assert challenge.verification["report"]["suite"]["sha256"] == challenge.suite_hash


def test_challenge_load_refuses_a_failed_report_naming_the_task(env: Path) -> None:
    suite = suite_copy(env, SUITE)
    write_report(suite, reference_successes=0)
    r = runner.invoke(app, ["challenge", "load", str(suite)])
    assert r.exit_code == 1, r.output
    assert "PickCube-v1: the reference solved 0 of 10 episodes (0%)" in r.output


def test_a_suite_changed_after_its_verification_must_be_verified_again(env: Path) -> None:
    suite = suite_copy(env, SUITE)
    write_report(suite)
    suite.write_text(suite.read_text().replace("budget_s: 300", "budget_s: 400"))
    r = runner.invoke(app, ["challenge", "load", str(suite)])
    assert r.exit_code == 1, r.output
    assert "is of another suite" in r.output
    # How it is checked is no part of what it names: new thresholds need no new report.
    suite.write_text(SUITE.read_text() + "verification: {reference_min_success: 0.8}\n")
    assert runner.invoke(app, ["challenge", "load", str(suite)]).exit_code == 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["maniskill-core", "--reference", "nope"], "no bundled policy of that name (bundled: "),
        (["no-such-suite", "--reference", "scripted"], "no suite file"),
        (["maniskill-core"], "Missing option '--reference'"),
    ],
)
def test_challenge_verify_errors(args: list[str], message: str) -> None:
    r = runner.invoke(app, ["challenge", "verify", *args])
    assert r.exit_code == 2, r.output
    assert message in r.output
