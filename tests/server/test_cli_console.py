"""The console's commands on the server's host: `manieval admin users|disable|enable|verify`,
`manieval challenge set|phase`; each change audited as the command line's."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session
from typer.testing import CliRunner

from manieval.cli import app
from server import audit
from server.kit.db import make_engine, session_factory
from server.models import Challenge, Phase, User
from testkit.factories import SUITE, make_user

runner = CliRunner()


@pytest.fixture
def data(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)])
    assert r.exit_code == 0, r.output
    with _db(tmp_path) as db:
        make_user(db, "alice")
        make_user(db, "bob", verified=False)
    return tmp_path


def _db(data: Path) -> Session:
    return session_factory(make_engine(f"sqlite:///{data / 'manieval.db'}"))()


@pytest.fixture
def db(data: Path) -> Iterator[Session]:
    with _db(data) as session:
        yield session


def test_admin_commands_disable_enable_verify_and_list_accounts(data: Path, db: Session) -> None:
    r = runner.invoke(app, ["admin", "disable", "alice"])
    assert r.exit_code == 2  # --reason is required
    r = runner.invoke(app, ["admin", "disable", "alice", "--reason", "   "])
    assert r.exit_code == 1
    assert "a reason is required" in r.output
    r = runner.invoke(app, ["admin", "disable", "Alice", "--reason", "sold their account"])
    assert r.exit_code == 0, r.output
    assert "alice is disabled" in r.output.lower()
    r = runner.invoke(app, ["admin", "users", "ali"])
    assert r.exit_code == 0, r.output
    assert "disabled: sold their account" in r.output
    assert "bob" not in r.output
    r = runner.invoke(app, ["admin", "enable", "alice"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["admin", "verify", "bob"])
    assert r.exit_code == 0, r.output
    assert runner.invoke(app, ["admin", "verify", "bob"]).exit_code == 1  # already
    assert runner.invoke(app, ["admin", "verify", "nobody"]).exit_code == 1
    bob = db.scalar(select(User).where(User.username == "bob"))
    assert bob is not None
    assert bob.email_verified
    records = audit.records(db, target_kind="user")
    assert [r.action for r in records] == ["user.verify", "user.enable", "user.disable"]
    assert {r.actor for r in records} == {audit.command_line_actor()}


def test_challenge_set_and_phase_change_quotas_and_dates(data: Path, db: Session) -> None:
    r = runner.invoke(app, ["challenge", "set", "server-tiny", "--quota-per-day", "7"])
    assert r.exit_code == 0, r.output
    assert "7 submissions a day, 1 at once" in r.output
    r = runner.invoke(app, ["challenge", "set", "server-tiny", "--quota-concurrent", "0"])
    assert r.exit_code == 1
    r = runner.invoke(
        app, ["challenge", "phase", "server-tiny", "test", "--closes", "2090-01-02T03:04"]
    )
    assert r.exit_code == 0, r.output
    assert "closes 2090-01-02 03:04 UTC" in r.output
    r = runner.invoke(app, ["challenge", "phase", "server-tiny", "test", "--opens", "2091-01-01"])
    assert r.exit_code == 1
    assert "after the opening date" in r.output
    r = runner.invoke(app, ["challenge", "phase", "server-tiny", "test", "--closes", "soon"])
    assert r.exit_code == 2
    r = runner.invoke(app, ["challenge", "phase", "server-tiny", "test", "--closes", "none"])
    assert r.exit_code == 0, r.output
    assert "closes never" in r.output
    challenge = db.scalar(select(Challenge).where(Challenge.slug == "server-tiny"))
    assert challenge is not None
    assert challenge.quota_per_day == 7
    test = db.scalar(select(Phase).where(Phase.challenge_id == challenge.id, Phase.name == "test"))
    assert test is not None
    assert test.closes_at is None
    first = audit.records(db, action="phase.settings")[-1]
    assert first.detail is not None
    assert first.detail["new"] == {"closes_at": datetime(2090, 1, 2, 3, 4, tzinfo=UTC).isoformat()}
