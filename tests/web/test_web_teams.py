"""Team pages: create a team, invite a member, accept, leave, with the CSRF forms; errors shown
on the form; the team on the account page and in the navigation."""

from __future__ import annotations

import re
from typing import Any

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from testkit.factories import make_user
from tests.web.helpers import browser, csrf_of


def _post(page: TestClient, url: str, form_page: str, **data: str) -> Any:
    return page.post(url, data={**data, "csrf_token": csrf_of(page.get(form_page).text)})


def test_create_invite_accept_and_leave_through_the_forms(client: TestClient, db: Session) -> None:
    make_user(db, "alice")
    make_user(db, "bob")
    alice, bob = browser(client, "alice"), browser(client, "bob")

    page = alice.get("/team").text
    assert "Create a team" in page
    r = _post(alice, "/team", "/team", name="grasp-lab", display_name="Grasp Lab")
    assert r.status_code == 303
    assert r.headers["location"] == "/teams/grasp-lab?done=created"
    team_page = alice.get(r.headers["location"]).text
    assert "Your team is created" in team_page
    assert (
        'You are the admin of\n    <a href="/teams/grasp-lab">Grasp Lab</a>'
        in alice.get("/team").text
    )
    assert "Invite a member" in team_page

    r = _post(alice, "/teams/grasp-lab/invitations", "/teams/grasp-lab", username="bob")
    assert r.status_code == 303
    assert "Pending invitations" in alice.get("/teams/grasp-lab").text

    mine = bob.get("/team").text
    found = re.search(r'action="/team/invitations/(\d+)/accept"', mine)
    assert found, mine
    assert "Grasp Lab" in mine
    r = bob.post(f"/team/invitations/{found.group(1)}/accept", data={"csrf_token": csrf_of(mine)})
    assert r.status_code == 303
    shown = bob.get(r.headers["location"]).text
    assert "You joined the team" in shown
    assert "Invite a member" not in shown  # a member, not the admin
    assert "Leave the team" in shown
    assert "You are a member of" in bob.get("/team").text
    assert '<a href="/teams/grasp-lab">Grasp Lab</a>' in bob.get("/account").text
    assert 'href="/team"' in bob.get("/account").text

    r = _post(bob, "/team/leave", "/team")
    assert r.headers["location"] == "/team?done=left"
    assert "You left the team." in bob.get("/team?done=left").text
    # Anonymous visitors see the members, not the admin's forms.
    anonymous = client.get("/teams/grasp-lab").text
    assert "alice" in anonymous
    assert "Invite a member" not in anonymous


def test_form_errors_show_on_the_form_with_a_200(client: TestClient, db: Session) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    r = _post(alice, "/team", "/team", name="Bad Name", display_name="X")
    assert r.status_code == 200
    assert "A team name may contain only" in r.text
    assert 'value="Bad Name"' in r.text
    _post(alice, "/team", "/team", name="grasp-lab", display_name="Grasp Lab")
    r = _post(alice, "/teams/grasp-lab/invitations", "/teams/grasp-lab", username="nobody")
    assert r.status_code == 200
    assert "no such user" in r.text


def test_team_pages_need_a_login_and_a_csrf_token(client: TestClient, db: Session) -> None:
    make_user(db, "alice")
    anonymous = browser(client)
    r = anonymous.get("/team")
    assert r.status_code == 303
    assert r.headers["location"].startswith("/login")
    alice = browser(client, "alice")
    r = alice.post("/team", data={"name": "grasp-lab", "display_name": "G"})
    assert r.status_code == 403
    assert anonymous.get("/teams/nobody-here").status_code == 404
    assert 'href="/team"' in alice.get("/").text  # the navigation


def _team_of_two(client: TestClient, db: Session) -> tuple[TestClient, TestClient]:
    """alice's team grasp-lab with bob in it and carol invited; their browsers."""
    for name in ("alice", "bob", "carol"):
        make_user(db, name)
    alice, bob = browser(client, "alice"), browser(client, "bob")
    _post(alice, "/team", "/team", name="grasp-lab", display_name="Grasp Lab")
    _post(alice, "/teams/grasp-lab/invitations", "/teams/grasp-lab", username="bob")
    mine = bob.get("/team").text
    found = re.search(r'action="/team/invitations/(\d+)/accept"', mine)
    assert found, mine
    bob.post(f"/team/invitations/{found.group(1)}/accept", data={"csrf_token": csrf_of(mine)})
    _post(alice, "/teams/grasp-lab/invitations", "/teams/grasp-lab", username="carol")
    return alice, bob


def test_creating_a_team_from_a_stale_tab_says_why_not(client: TestClient, db: Session) -> None:
    alice, _bob = _team_of_two(client, db)
    # The create form was open before alice made her team; she posts it now.
    r = _post(alice, "/team", "/account", name="second", display_name="Second")
    assert r.status_code == 200
    assert "leave it first (a user is in one team at a time)" in r.text


def test_a_member_posting_the_admin_forms_is_told_only_the_admin_can(
    client: TestClient, db: Session
) -> None:
    alice, bob = _team_of_two(client, db)
    found = re.search(
        r'/teams/grasp-lab/invitations/(\d+)/revoke"', alice.get("/teams/grasp-lab").text
    )
    assert found
    for url in (
        f"/teams/grasp-lab/invitations/{found.group(1)}/revoke",
        "/teams/grasp-lab/members/alice/remove",
    ):
        r = _post(bob, url, "/teams/grasp-lab")
        assert r.status_code == 200, url
        assert "only the admin of team" in r.text, url
    assert "Revoke" in alice.get("/teams/grasp-lab").text  # the invitation is still there


def test_a_site_admin_sees_pending_invitations_without_the_admin_forms(
    client: TestClient, db: Session
) -> None:
    _team_of_two(client, db)
    make_user(db, "root-admin", admin=True)
    page = browser(client, "root-admin").get("/teams/grasp-lab").text
    assert "Pending invitations" in page
    assert '<th scope="row">carol</th>' in page
    assert "Invite a member" not in page
    assert "/revoke" not in page
    assert "/remove" not in page
    assert "Only the team's admin can invite members or revoke an invitation." in page
