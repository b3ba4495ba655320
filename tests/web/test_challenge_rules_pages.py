"""The challenge rules on the web: a participant marks a final choice on the submission's page;
organizers close a phase and publish its hidden board from the leaderboard page, which tells a
participant the board is hidden; the post-deadline board has a page of its own."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.challenges.service import get_challenge
from server.models import Submission, User
from testkit.factories import make_user
from tests.server.test_challenge_rules import _challenge, _done
from tests.web.helpers import browser, csrf_of

BOARD = "/challenges/server-tiny/leaderboard?phase=test"


def _evaluated(sessions: sessionmaker[Session], username: str) -> int:
    with sessions() as db:
        user = db.scalar(select(User).where(User.username == username))
        assert user is not None
        return _done(db, user, get_challenge(db, slug="server-tiny"), [True, False]).id


def _post(page: TestClient, at: str, action: str, **fields: str) -> int:
    token = csrf_of(page.get(at).text)
    return page.post(action, data={"csrf_token": token, **fields}).status_code


def test_the_rules_on_the_pages(
    client: TestClient, sessions: sessionmaker[Session], tmp_path: Path
) -> None:
    with sessions() as db:
        _challenge(db, tmp_path)
        make_user(db, "alice")
        make_user(db, "judge", admin=True)
    sid = _evaluated(sessions, "alice")
    alice, judge = browser(client, "alice"), browser(client, "judge")

    page = alice.get(f"/submissions/{sid}").text
    assert "Mark as my final choice" in page
    assert _post(alice, f"/submissions/{sid}", f"/submissions/{sid}/final", final="true") == 303
    assert "Take off the final mark" in alice.get(f"/submissions/{sid}").text
    with sessions() as db:
        assert db.get(Submission, sid).final_for is not None  # type: ignore[union-attr]

    assert "you see only your own rows" in alice.get(BOARD).text
    assert "Publish the board" not in alice.get(BOARD).text
    assert _post(alice, BOARD, "/challenges/server-tiny/close", phase="test") == 403
    assert "Publish the board" in judge.get(BOARD).text
    assert _post(judge, BOARD, "/challenges/server-tiny/close", phase="test") == 303
    assert "Mark as my final choice" not in alice.get(f"/submissions/{sid}").text
    late = _evaluated(sessions, "alice")
    assert "post-deadline board" in alice.get(f"/submissions/{late}").text
    assert f"#{late}" in alice.get("/challenges/server-tiny/post-deadline?phase=test").text
    assert _post(judge, BOARD, "/challenges/server-tiny/publish", phase="test") == 303
    assert "hidden until the organizers publish" not in browser(client).get(BOARD).text
