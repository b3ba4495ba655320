"""The challenge rules from the command line against a real server: a participant marks a
final choice, sees only their own row of a hidden board, and reads the post-deadline board
after an organizer closes the phase."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from manieval.cli import app
from manieval.errors import ExitCode
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from tests.cli.conftest import LiveServer, participant, running_server
from tests.server.test_challenge_rules import rules_suite

pytestmark = pytest.mark.sim
ACCEPTED = re.compile(r"submission (\d+)")


@pytest.fixture(scope="module")
def ruled(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    data = tmp_path_factory.mktemp("server")
    settings = Settings(dev_mode=True, data_dir=data, cookie_secure=False)
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        options = ChallengeOptions(quota_per_day=50, quota_concurrent=3)
        load_challenge(db, rules_suite(data), options, seed_secret=settings.secret("seed_secret"))
    with running_server(data, challenges=False) as server:
        yield server


def _submitted(output: str) -> str:
    found = ACCEPTED.search(output)
    assert found is not None, output
    return found[1]


def test_final_choice_hidden_board_and_post_deadline_board(
    ruled: LiveServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    alice = participant(ruled, tmp_path / "alice", "alice")
    test = ("-c", "server-tiny", "--phase", "test", "--wait")
    r = alice.run("submit", "local:scripted", *test)
    assert r.exit_code == 0, r.output
    sid = _submitted(r.output)

    r = alice.run("final", sid)
    assert r.exit_code == 0, r.output
    assert f"submission {sid} is your final choice in phase test" in r.stderr
    r = alice.run("leaderboard", "server-tiny", "--phase", "test", "--json")
    assert r.exit_code == 0, r.output
    assert '"rank":null' in r.stdout.replace(" ", "")  # her own row, unranked: hidden
    r = alice.run("final", sid, "--clear")
    assert "is no longer your final choice" in r.stderr

    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(ruled.data_dir))
    r = CliRunner().invoke(app, ["challenge", "close", "server-tiny", "test"])
    assert r.exit_code == 0, r.output
    r = alice.run("final", sid)
    assert r.exit_code == ExitCode.CONFLICT, r.output
    r = alice.run("submit", "local:scripted", *test)
    assert r.exit_code == 0, r.output
    late = _submitted(r.output)
    r = alice.run("post-deadline", "server-tiny", "--phase", "test")
    assert r.exit_code == 0, r.output
    assert f"#{late}" in r.stdout
