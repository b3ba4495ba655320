"""Teams through the API: create, invite, accept, decline, revoke, leave, remove; a user in
one team at a time; the admin role handed on; an emptied team dissolved."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.kit.errors import NotFound
from server.models import Team, TeamInvitation, User
from server.teams import service as teams
from testkit.factories import make_user, token_for

API = "/api/v1"


@pytest.fixture
def auth(client: TestClient, db: Session) -> dict[str, dict[str, str]]:
    for name in ("alice", "bob", "carol"):
        make_user(db, name)
    return {name: token_for(client, name) for name in ("alice", "bob", "carol")}


def _create(client: TestClient, headers: dict[str, str], name: str = "grasp-lab") -> None:
    r = client.post(
        f"{API}/teams", json={"name": name, "display_name": "Grasp Lab"}, headers=headers
    )
    assert r.status_code == 201, r.text


def _invite(client: TestClient, headers: dict[str, str], username: str) -> int:
    r = client.post(
        f"{API}/teams/grasp-lab/invitations", json={"username": username}, headers=headers
    )
    assert r.status_code == 201, r.text
    invitation_id: int = r.json()["id"]
    return invitation_id


def test_create_invite_accept_shows_both_members(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    r = client.post(
        f"{API}/teams",
        json={"name": "grasp-lab", "display_name": " Grasp Lab "},
        headers=auth["alice"],
    )
    assert r.status_code == 201, r.text
    assert r.json()["display_name"] == "Grasp Lab"
    assert [(m["username"], m["is_admin"]) for m in r.json()["members"]] == [("alice", True)]
    invitation_id = _invite(client, auth["alice"], "bob")

    mine = client.get(f"{API}/team", headers=auth["bob"]).json()
    assert mine["team"] is None
    assert [(i["id"], i["team"], i["invited_by"]) for i in mine["invitations"]] == [
        (invitation_id, "grasp-lab", "alice")
    ]
    # The admin sees the pending invitation; others and anonymous visitors do not.
    assert [
        i["username"]
        for i in client.get(f"{API}/teams/grasp-lab", headers=auth["alice"]).json()["invitations"]
    ] == ["bob"]
    assert client.get(f"{API}/teams/grasp-lab").json()["invitations"] is None

    r = client.post(f"{API}/team/invitations/{invitation_id}/accept", headers=auth["bob"])
    assert r.status_code == 200, r.text
    assert [(m["username"], m["is_admin"]) for m in r.json()["members"]] == [
        ("alice", True),
        ("bob", False),
    ]
    assert client.get(f"{API}/team", headers=auth["bob"]).json()["team"]["name"] == "grasp-lab"
    # Single use: the invitation is gone; bob, in the team now, is told so first.
    again = client.post(f"{API}/team/invitations/{invitation_id}/accept", headers=auth["bob"])
    assert again.status_code == 409
    assert "you are in team 'grasp-lab'" in again.json()["error"]["message"]


def test_a_user_is_in_one_team_at_a_time(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    _create(client, auth["alice"])
    r = client.post(
        f"{API}/teams", json={"name": "second", "display_name": "Second"}, headers=auth["alice"]
    )
    assert r.status_code == 409
    assert "leave it first" in r.json()["error"]["message"]
    _create(client, auth["bob"], "bobs")
    invitation_id = _invite(client, auth["alice"], "bob")
    r = client.post(f"{API}/team/invitations/{invitation_id}/accept", headers=auth["bob"])
    assert r.status_code == 409
    assert client.post(f"{API}/team/leave", headers=auth["bob"]).json() == {
        "team": "bobs",
        "dissolved": True,
    }
    r = client.post(f"{API}/team/invitations/{invitation_id}/accept", headers=auth["bob"])
    assert r.status_code == 200


def test_team_names_follow_the_user_name_grammar_and_are_unique(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    for bad in ("Caps", "a", "-lead", "sp ace", "x\u0000y"):
        r = client.post(
            f"{API}/teams", json={"name": bad, "display_name": "X"}, headers=auth["alice"]
        )
        assert r.status_code == 422, bad
    r = client.post(
        f"{API}/teams", json={"name": "fine", "display_name": "   "}, headers=auth["alice"]
    )
    assert r.status_code == 422
    assert "display_name" in r.json()["error"]["fields"]
    # A team must not pass for the service or its staff, as a user must not.
    for reserved in ("admin", "staff", "official", "manieval", "team"):
        r = client.post(
            f"{API}/teams", json={"name": reserved, "display_name": "X"}, headers=auth["alice"]
        )
        assert r.status_code == 422, reserved
        assert "reserved" in r.json()["error"]["fields"]["name"]
    _create(client, auth["alice"], "taken")
    r = client.post(
        f"{API}/teams", json={"name": "taken", "display_name": "X"}, headers=auth["bob"]
    )
    assert r.status_code == 409
    assert r.json()["error"]["fields"] == {"name": "taken"}


def test_only_the_admin_invites_revokes_and_removes(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    _create(client, auth["alice"])
    bob_invitation = _invite(client, auth["alice"], "bob")
    client.post(f"{API}/team/invitations/{bob_invitation}/accept", headers=auth["bob"])
    r = client.post(
        f"{API}/teams/grasp-lab/invitations", json={"username": "carol"}, headers=auth["bob"]
    )
    assert r.status_code == 403
    carol_invitation = _invite(client, auth["alice"], "carol")
    assert (
        client.post(
            f"{API}/teams/grasp-lab/invitations", json={"username": "carol"}, headers=auth["alice"]
        ).status_code
        == 409
    )
    assert (
        client.post(
            f"{API}/teams/grasp-lab/invitations", json={"username": "nobody"}, headers=auth["alice"]
        ).status_code
        == 404
    )
    assert (
        client.post(
            f"{API}/teams/grasp-lab/invitations", json={"username": "bob"}, headers=auth["alice"]
        ).status_code
        == 409
    )
    assert (
        client.delete(
            f"{API}/teams/grasp-lab/invitations/{carol_invitation}", headers=auth["bob"]
        ).status_code
        == 403
    )
    assert (
        client.delete(
            f"{API}/teams/grasp-lab/invitations/{carol_invitation}", headers=auth["alice"]
        ).status_code
        == 200
    )
    # A revoked invitation cannot be accepted.
    assert (
        client.post(
            f"{API}/team/invitations/{carol_invitation}/accept", headers=auth["carol"]
        ).status_code
        == 404
    )
    assert (
        client.delete(f"{API}/teams/grasp-lab/members/alice", headers=auth["bob"]).status_code
        == 403
    )
    assert (
        client.delete(f"{API}/teams/grasp-lab/members/alice", headers=auth["alice"]).status_code
        == 409
    )
    assert (
        client.delete(f"{API}/teams/grasp-lab/members/carol", headers=auth["alice"]).status_code
        == 404
    )
    assert (
        client.delete(f"{API}/teams/grasp-lab/members/bob", headers=auth["alice"]).status_code
        == 200
    )
    assert client.get(f"{API}/team", headers=auth["bob"]).json()["team"] is None


def test_declining_deletes_the_invitation(
    client: TestClient, auth: dict[str, dict[str, str]], db: Session
) -> None:
    _create(client, auth["alice"])
    invitation_id = _invite(client, auth["alice"], "bob")
    assert (
        client.post(
            f"{API}/team/invitations/{invitation_id}/decline", headers=auth["carol"]
        ).status_code
        == 404
    )
    assert (
        client.post(
            f"{API}/team/invitations/{invitation_id}/decline", headers=auth["bob"]
        ).status_code
        == 200
    )
    assert db.scalar(select(TeamInvitation).where(TeamInvitation.id == invitation_id)) is None
    assert client.get(f"{API}/team", headers=auth["bob"]).json()["invitations"] == []


def test_the_admin_leaving_hands_the_role_on_and_the_last_member_dissolves(
    client: TestClient, auth: dict[str, dict[str, str]], db: Session
) -> None:
    _create(client, auth["alice"])
    for name in ("bob", "carol"):
        invitation_id = _invite(client, auth["alice"], name)
        client.post(f"{API}/team/invitations/{invitation_id}/accept", headers=auth[name])
    assert client.post(f"{API}/team/leave", headers=auth["alice"]).json() == {
        "team": "grasp-lab",
        "dissolved": False,
    }
    members = client.get(f"{API}/teams/grasp-lab").json()["members"]
    assert [(m["username"], m["is_admin"]) for m in members] == [("bob", True), ("carol", False)]
    client.post(f"{API}/team/leave", headers=auth["bob"])
    client.post(f"{API}/team/leave", headers=auth["carol"])
    assert client.get(f"{API}/teams/grasp-lab").status_code == 404
    # The dissolved team's row stays (its submissions keep pointing at it), its name freed.
    (gone,) = db.scalars(select(Team).where(Team.display_name == "Grasp Lab")).all()
    assert (gone.name, gone.dissolved_at is not None) == (f"~{gone.id}", True)
    r = client.post(f"{API}/team/leave", headers=auth["carol"])
    assert r.status_code == 409
    _create(client, auth["bob"], "grasp-lab")
    assert client.get(f"{API}/teams/grasp-lab").json()["members"][0]["username"] == "bob"


def test_a_site_admin_sees_invitations_but_only_the_team_admin_acts(
    client: TestClient, auth: dict[str, dict[str, str]], db: Session
) -> None:
    make_user(db, "root-admin", admin=True)
    site_admin = token_for(client, "root-admin")
    _create(client, auth["alice"])
    invitation_id = _invite(client, auth["alice"], "bob")
    shown = client.get(f"{API}/teams/grasp-lab", headers=site_admin).json()["invitations"]
    assert [i["username"] for i in shown] == ["bob"]
    r = client.delete(f"{API}/teams/grasp-lab/invitations/{invitation_id}", headers=site_admin)
    assert r.status_code == 403


def test_team_endpoints_need_a_login(client: TestClient) -> None:
    assert client.get(f"{API}/team").status_code == 401
    assert client.post(f"{API}/teams", json={"name": "abc", "display_name": "A"}).status_code == 401
    assert client.get(f"{API}/teams/nobody-here").status_code == 404


def test_acting_on_a_team_dissolved_meanwhile_is_a_404_naming_it(
    sessions: sessionmaker[Session],
) -> None:
    with sessions() as first:
        alice, bob = make_user(first, "alice"), make_user(first, "bob")
        team = teams.create_team(first, user=alice, name="grasp-lab", display_name="Grasp Lab")
        invitation_id = teams.invite(first, admin=alice, team=team, username="bob").id
        first.flush()
        with sessions() as second:  # another request, as a second tab would send it
            leaving = second.get(User, alice.id)
            assert leaving is not None
            gone = teams.leave(second, user=leaving)
            second.commit()
        assert gone is None
        with pytest.raises(NotFound, match="no team 'grasp-lab': it was dissolved"):
            teams.invite(first, admin=alice, team=team, username="bob")
        with pytest.raises(NotFound, match=f"no invitation {invitation_id} for you"):
            teams.accept(first, user=bob, invitation_id=invitation_id)
