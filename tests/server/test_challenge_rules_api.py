"""The challenge rules through the API (final mark, post-deadline board, a hidden board and its
publication, a phase's close) and the organizers' `manieval challenge close|publish`."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from manieval.cli import app
from server.challenges.service import get_challenge
from server.models import User
from testkit.factories import make_user, token_for
from tests.server.test_challenge_rules import _challenge, _done, rules_suite


@pytest.fixture
def ready(sessions: sessionmaker[Session], tmp_path: Path) -> None:
    with sessions() as db:
        _challenge(db, tmp_path)
        make_user(db, "alice")
        make_user(db, "bob")
        make_user(db, "organizer", admin=True)


def _evaluated(sessions: sessionmaker[Session], username: str, successes: list[bool]) -> int:
    with sessions() as db:
        user = db.scalar(select(User).where(User.username == username))
        assert user is not None
        return _done(db, user, get_challenge(db, slug="server-tiny"), successes).id


def _board(client: TestClient, headers: dict[str, str] | None = None) -> list[tuple[object, str]]:
    r = client.get(
        "/api/v1/challenges/server-tiny/leaderboard", params={"phase": "test"}, headers=headers
    )
    assert r.status_code == 200, r.text
    return [(row["rank"], row["username"]) for row in r.json()["items"]]


def test_a_participant_marks_a_final_choice_and_takes_it_off(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    first = _evaluated(sessions, "alice", [True, True])
    _evaluated(sessions, "alice", [False, False])
    headers = token_for(client, "alice")
    r = client.put(f"/api/v1/submissions/{first}/final", headers=headers)
    assert r.status_code == 200, r.text
    assert r.json()["final"] is True
    r = client.put(f"/api/v1/submissions/{first}/final", headers=token_for(client, "bob"))
    assert r.status_code == 404  # not bob's
    r = client.delete(f"/api/v1/submissions/{first}/final", headers=headers)
    assert r.json()["final"] is False


def test_a_hidden_board_shows_the_caller_their_rows_until_published(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    _evaluated(sessions, "alice", [True, False])
    _evaluated(sessions, "bob", [True, True])
    assert _board(client) == []
    assert _board(client, token_for(client, "alice")) == [(None, "alice")]
    admin = token_for(client, "organizer")
    assert _board(client, admin) == [(1, "bob"), (2, "alice")]
    r = client.post("/api/v1/challenges/server-tiny/phases/test/publish", headers=admin)
    assert r.status_code == 200, r.text
    test = next(p for p in r.json()["phases"] if p["name"] == "test")
    assert test["board"] == "hidden"
    assert test["published_at"] is not None
    assert _board(client) == [(1, "bob"), (2, "alice")]


def test_only_organizers_close_or_publish(client: TestClient, ready: None) -> None:
    headers = token_for(client, "alice")
    for action in ("close", "publish"):
        r = client.post(f"/api/v1/challenges/server-tiny/phases/test/{action}", headers=headers)
        assert r.status_code == 403, r.text


def test_after_a_close_submissions_are_late_and_ranked_apart(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    admin = token_for(client, "organizer")
    r = client.post("/api/v1/challenges/server-tiny/phases/test/close", headers=admin)
    assert r.status_code == 200, r.text
    r = client.post("/api/v1/challenges/server-tiny/phases/test/close", headers=admin)
    assert r.status_code == 409  # closed already
    late = _evaluated(sessions, "bob", [True, True])
    r = client.get("/api/v1/challenges/server-tiny/post-deadline", params={"phase": "test"})
    assert r.json()["items"] == []  # hidden, not published: nobody's rows for anonymous
    r = client.get(
        "/api/v1/challenges/server-tiny/post-deadline",
        params={"phase": "test"},
        headers=token_for(client, "bob"),
    )
    assert [(i["rank"], i["submission_id"]) for i in r.json()["items"]] == [(None, late)]
    assert _board(client, admin) == []  # never on the official board
    r = client.get("/api/v1/challenges/server-tiny/post-deadline", params={"phase": "dev"})
    assert r.status_code == 404  # the dev phase refuses late ones


def test_organizers_close_and_publish_from_the_command_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    runner = CliRunner()
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(rules_suite(tmp_path))])
    assert r.exit_code == 0, r.output
    assert "last counts, final choice, late ones to a post-deadline board" in r.output
    r = runner.invoke(app, ["challenge", "close", "server-tiny", "test"])
    assert r.exit_code == 0, r.output
    assert "later submissions go to its post-deadline board" in r.output
    r = runner.invoke(app, ["challenge", "publish", "server-tiny", "test"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["challenge", "publish", "server-tiny", "dev"])
    assert r.exit_code == 1
    assert "public board: nothing to publish" in r.output
