"""A board hidden until published hides its submissions too: another participant and an
anonymous reader get 404 for a submission's detail, episodes, videos, trajectories and live
events (as for its row), its owner, its team (team mode) and admins see it, everyone once the
board is published (docs/server.md, Challenge rules)."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.challenges.service import get_challenge, publish_board
from server.models import Submission, Team, TeamMember, User
from server.submissions.service import visible_to
from testkit.factories import make_user, token_for
from tests.server.test_challenge_rules_api import _evaluated, ready

__all__ = ["ready"]  # the fixture, imported to be used here

ROUTES = ("", "/episodes", "/videos", "/trajectories")


def _statuses(client: TestClient, sid: int, headers: dict[str, str] | None) -> list[object]:
    """Each route's status, "unseen" for a 404 that denies the submission exists."""
    answers = [client.get(f"/api/v1/submissions/{sid}{route}", headers=headers) for route in ROUTES]
    return ["unseen" if f"no submission {sid}" in r.text else r.status_code for r in answers]


def test_others_get_404_for_a_hidden_boards_submission_until_published(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    sid = _evaluated(sessions, "alice", [True, False])
    bob, alice = token_for(client, "bob"), token_for(client, "alice")
    admin = token_for(client, "organizer")
    assert _statuses(client, sid, None) == ["unseen"] * 4
    assert _statuses(client, sid, bob) == ["unseen"] * 4
    for page in ("", "/outcome", "/events"):  # the web page, its parts, its live events
        assert client.get(f"/submissions/{sid}{page}").status_code == 404
    # its owner sees it all; trajectories of a secret-seed phase are the organizers' only
    assert _statuses(client, sid, alice) == [200, 200, 200, 403]
    assert client.get(f"/api/v1/submissions/{sid}", headers=alice).json()["score"] is not None
    assert _statuses(client, sid, admin) == [200, 200, 200, 404]  # none recorded here

    r = client.post("/api/v1/challenges/server-tiny/phases/test/publish", headers=admin)
    assert r.status_code == 200, r.text
    # published: a public submission is everyone's to see, its private parts still its owner's
    assert _statuses(client, sid, bob) == [200, 403, 200, 403]
    assert client.get(f"/api/v1/submissions/{sid}").status_code == 200
    assert client.get(f"/submissions/{sid}").status_code == 200


def test_a_public_boards_submission_is_everyones_to_see(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    with sessions() as db:
        test = next(p for p in get_challenge(db, slug="server-tiny").phases if p.name == "test")
        test.board = "public"
        db.commit()
    sid = _evaluated(sessions, "alice", [True, True])
    assert client.get(f"/api/v1/submissions/{sid}").status_code == 200


def test_a_team_sees_its_members_submissions_on_a_hidden_board(
    sessions: sessionmaker[Session], ready: None
) -> None:
    sid = _evaluated(sessions, "alice", [True])
    with sessions() as db:
        users = {u.username: u for u in db.scalars(select(User))}
        carol = make_user(db, "carol")
        team = Team(name="grippers", display_name="Grippers")
        db.add(team)
        db.flush()
        db.add_all([TeamMember(user_id=u.id, team_id=team.id) for u in (users["alice"], carol)])
        challenge = get_challenge(db, slug="server-tiny")
        s = db.get(Submission, sid)
        assert s is not None
        s.team_id = team.id
        assert not visible_to(db, s, carol)  # not a team-mode challenge: rows are each user's
        challenge.team_mode = True
        db.flush()
        assert visible_to(db, s, carol)
        assert not visible_to(db, s, users["bob"])
        assert not visible_to(db, s, None)
        publish_board(db, by=None, slug="server-tiny", phase="test")
        assert visible_to(db, s, users["bob"])
        assert visible_to(db, s, None)


def test_a_private_submission_stays_its_owners_after_publication(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    sid = _evaluated(sessions, "alice", [True])
    with sessions() as db:
        s = db.get(Submission, sid)
        assert s is not None
        s.public = False
        publish_board(db, by=None, slug="server-tiny", phase="test")
        db.commit()
    assert client.get(f"/api/v1/submissions/{sid}").status_code == 404
    alice = token_for(client, "alice")
    assert client.get(f"/api/v1/submissions/{sid}", headers=alice).status_code == 200
