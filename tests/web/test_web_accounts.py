"""Register, log in and out, and API tokens through the pages."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from tests.factories import PASSWORD, make_user
from tests.web.helpers import browser, csrf_of

TOKEN = re.compile(r"mev_[a-z2-7]{8}_[A-Za-z0-9_-]{43}")


def register(client: TestClient, **fields: str) -> object:
    form = {"username": "alice", "email": "alice@example.org", "password": PASSWORD}
    form.update(fields)
    token = csrf_of(client.get("/register").text)
    return client.post("/register", data={"csrf_token": token, **form})


def test_register_logs_in_and_goes_to_the_account_page(client: TestClient) -> None:
    visitor = browser(client)
    r = register(visitor, next="/challenges/server-tiny")
    assert r.status_code == 303  # type: ignore[attr-defined]
    assert r.headers["location"] == "/challenges/server-tiny"  # type: ignore[attr-defined]
    account = visitor.get("/account")
    assert account.status_code == 200
    assert "alice@example.org" in account.text


@pytest.mark.parametrize(
    ("fields", "field", "words"),
    [
        ({"username": "Al"}, "username", "3 to 32"),
        ({"username": "admin"}, "username", "reserved"),
        ({"email": "not-an-email"}, "email", "email address"),
        ({"password": "password123456"}, "password", "common"),
    ],
)
def test_registration_problems_are_shown_next_to_their_field(
    client: TestClient, fields: dict[str, str], field: str, words: str
) -> None:
    r = register(browser(client), **fields)
    assert r.status_code == 200  # type: ignore[attr-defined]  # the form again, not an error
    html = r.text  # type: ignore[attr-defined]
    error = re.search(rf'<p class="field-error" id="{field}-error">([^<]*)</p>', html)
    assert error
    assert words in error.group(1)
    assert re.search(rf'id="{field}"[^>]*aria-describedby="[^"]*{field}-error"', html)
    assert re.search(rf'id="{field}"[^>]*aria-invalid="true"', html)
    assert PASSWORD not in html  # a password is never sent back


def test_a_taken_username_is_a_conflict_on_its_field(client: TestClient, db: Session) -> None:
    make_user(db, "alice")
    r = register(browser(client), email="other@example.org")
    assert r.status_code == 200  # type: ignore[attr-defined]
    assert 'id="username-error">already taken' in r.text  # type: ignore[attr-defined]


def test_login_failures_say_one_thing_and_success_follows_next(
    client: TestClient, db: Session
) -> None:
    make_user(db, "alice")
    visitor = browser(client)
    for login in ("alice", "nobody"):
        token = csrf_of(visitor.get("/login").text)
        r = visitor.post("/login", data={"csrf_token": token, "login": login, "password": "x" * 12})
        assert r.status_code == 200  # the form again: a browser logs any 4xx as an error
        assert "Wrong username, email or password." in r.text
    token = csrf_of(visitor.get("/login").text)
    ok = visitor.post(
        "/login",
        data={"csrf_token": token, "login": "ALICE@example.org", "password": PASSWORD, "next": "/"},
    )
    assert ok.status_code == 303
    assert ok.headers["location"] == "/"
    assert "httponly" in ok.headers["set-cookie"].lower()
    assert "Account (alice)" in visitor.get("/").text


@pytest.mark.parametrize("target", ["//evil.example/x", "https://evil.example/", "/\\evil"])
def test_login_never_redirects_to_another_site(
    client: TestClient, db: Session, target: str
) -> None:
    make_user(db, "alice")
    visitor = browser(client)
    token = csrf_of(visitor.get("/login").text)
    r = visitor.post(
        "/login",
        data={"csrf_token": token, "login": "alice", "password": PASSWORD, "next": target},
    )
    assert r.headers["location"] == "/account"


def test_pages_that_need_an_account_send_to_the_login_page_and_back(client: TestClient) -> None:
    for path in ("/account", "/submissions", "/challenges/server-tiny/submit"):
        r = browser(client).get(path)
        assert r.status_code == 303
        assert r.headers["location"].startswith("/login?next=%2F")


def test_logout_ends_the_session(client: TestClient, db: Session) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    cookie = alice.cookies.get("manieval_session")
    r = alice.post("/logout", data={"csrf_token": csrf_of(alice.get("/").text)})
    assert r.status_code == 303
    assert alice.get("/account").status_code == 303
    replay = browser(client)
    replay.cookies.set("manieval_session", str(cookie))
    assert replay.get("/account").status_code == 303  # the old cookie is dead on the server


def test_a_new_token_is_shown_once_works_and_can_be_revoked(
    client: TestClient, db: Session
) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    page = alice.post(
        "/account/tokens", data={"csrf_token": csrf_of(alice.get("/account").text), "name": "ci"}
    )
    assert page.status_code == 201
    assert page.headers["cache-control"] == "no-store"
    found = TOKEN.search(page.text)
    assert found
    assert "will not be shown again" in page.text
    plaintext = found.group(0)
    again = alice.get("/account").text
    assert plaintext not in again
    assert ">ci</th>" in again
    bearer = {"Authorization": f"Bearer {plaintext}"}
    assert client.get("/api/v1/me", headers=bearer).json()["user"]["username"] == "alice"
    token_id = re.search(r'action="/account/tokens/(\d+)/revoke"', again)
    assert token_id
    r = alice.post(
        f"/account/tokens/{token_id.group(1)}/revoke", data={"csrf_token": csrf_of(again)}
    )
    assert r.status_code == 303
    assert "The token is revoked" in alice.get(r.headers["location"]).text
    assert client.get("/api/v1/me", headers=bearer).status_code == 401


def test_token_problems_are_shown_by_the_name_field_and_others_tokens_are_404(
    client: TestClient, db: Session
) -> None:
    make_user(db, "alice")
    make_user(db, "bob")
    alice, bob = browser(client, "alice"), browser(client, "bob")
    r = alice.post(
        "/account/tokens", data={"csrf_token": csrf_of(alice.get("/account").text), "name": " "}
    )
    assert r.status_code == 200
    assert 'id="name-error"' in r.text
    created = alice.post(
        "/account/tokens", data={"csrf_token": csrf_of(alice.get("/account").text), "name": "a"}
    )
    token_id = re.search(r'action="/account/tokens/(\d+)/revoke"', created.text)
    assert token_id
    theirs = bob.post(
        f"/account/tokens/{token_id.group(1)}/revoke",
        data={"csrf_token": csrf_of(bob.get("/account").text)},
    )
    assert theirs.status_code == 404
    assert "revoked" not in alice.get("/account").text.split("<tbody>")[1]


@pytest.mark.parametrize(
    "target",
    ["/\t/evil.example/x", "/\n/evil.example", "//evil.example", "/\\evil.example", "https://x.y/"],
)
def test_after_registering_no_next_leads_to_another_site(client: TestClient, target: str) -> None:
    r = register(browser(client), next=target)
    assert r.headers["location"] == "/account"  # type: ignore[attr-defined]


def test_a_form_cookie_token_opens_only_the_login_and_register_forms(
    client: TestClient, db: Session
) -> None:
    make_user(db, "alice")
    visitor = browser(client)
    anonymous = csrf_of(visitor.get("/login").text)  # bound to the form cookie, not a session
    r = visitor.post(
        "/login",
        data={"csrf_token": anonymous, "login": "alice", "password": PASSWORD, "next": "/"},
    )
    assert r.status_code == 303
    refused = visitor.post("/account/tokens", data={"csrf_token": anonymous, "name": "ci"})
    assert refused.status_code == 403
    fresh = csrf_of(visitor.get("/account").text)
    created = visitor.post("/account/tokens", data={"csrf_token": fresh, "name": "ci"})
    assert created.status_code == 201
