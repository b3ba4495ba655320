"""`manieval challenge load --teams` and `manieval challenge teams SLUG on|off`: the team-mode
setting of a challenge, kept across reloads unless named."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from manieval.cli import app
from server.kit.db import make_engine, session_factory
from server.models import Challenge
from testkit.factories import SUITE

runner = CliRunner()


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    return tmp_path


def _team_mode(data: Path) -> bool:
    with session_factory(make_engine(f"sqlite:///{data / 'manieval.db'}"))() as db:
        mode = db.scalar(select(Challenge.team_mode).where(Challenge.slug == "server-tiny"))
    assert mode is not None
    return mode


def test_team_mode_is_set_on_load_kept_on_reload_and_switched(env: Path) -> None:
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)])
    assert r.exit_code == 0, r.output
    assert _team_mode(env) is False
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE), "--teams"])
    assert r.exit_code == 0, r.output
    assert "(teams)" in r.output
    assert _team_mode(env) is True
    runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)])
    assert _team_mode(env) is True  # not named: kept
    r = runner.invoke(app, ["challenge", "teams", "server-tiny", "off"])
    assert r.exit_code == 0, r.output
    assert "count per user" in r.output
    assert _team_mode(env) is False


def test_challenge_teams_refuses_unknown_challenges_and_modes(env: Path) -> None:
    runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)])
    r = runner.invoke(app, ["challenge", "teams", "server-tiny", "maybe"])
    assert r.exit_code == 2
    r = runner.invoke(app, ["challenge", "teams", "nope", "on"])
    assert r.exit_code == 1
    assert "no challenge 'nope'" in r.output
