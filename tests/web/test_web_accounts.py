"""Register, log in and out, API tokens, and the mailed links (verify an address, reset a
password, change the address) through the pages, with the embedded default's folder mailer."""

from __future__ import annotations

import re
from datetime import UTC, datetime, timedelta
from email import message_from_bytes, policy
from email.message import EmailMessage
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update
from sqlalchemy.orm import Session

from server.kit.settings import Settings
from server.models.accounts import EmailToken
from testkit.factories import PASSWORD, make_challenge, make_user
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


# Mailed links ---------------------------------------------------------------------------------

LINK = re.compile(r"http://testserver(/[a-z-]+)\?token=([A-Za-z0-9_-]{43})")
NEW_PASSWORD = "purple submarine orchestra lantern"
BANNER = "Please verify your email address"


def mails_to(settings: Settings, address: str) -> list[EmailMessage]:
    """The mails the folder mailer wrote to `address`, oldest first."""
    found = []
    for path in sorted(
        (settings.data_dir / "mail").glob("*.eml"), key=lambda p: p.stat().st_mtime_ns
    ):
        message = message_from_bytes(path.read_bytes(), policy=policy.default)
        assert isinstance(message, EmailMessage)
        if message["To"] == address:
            found.append(message)
    return found


def link_in(message: EmailMessage) -> tuple[str, str]:
    """The (path, token) of the mail's link."""
    part = message.get_body(("plain",))
    assert part is not None
    found = LINK.search(str(part.get_content()))  # type: ignore[attr-defined]
    assert found, part
    return found.group(1), found.group(2)


def test_registering_mails_a_link_whose_page_verifies_only_by_its_button(
    client: TestClient, settings: Settings
) -> None:
    visitor = browser(client)
    register(visitor)
    account = visitor.get("/account")
    assert BANNER in account.text
    assert "(not verified)" in account.text
    [mail] = mails_to(settings, "alice@example.org")
    path, token = link_in(mail)
    assert path == "/verify"

    page = visitor.get(f"/verify?token={token}")  # what a mail scanner does: nothing is used
    assert "Confirm my address" in page.text
    assert BANNER in visitor.get("/account").text
    done = visitor.post("/verify", data={"csrf_token": csrf_of(page.text), "token": token})
    assert done.status_code == 200
    assert "alice@example.org</strong> is verified" in done.text
    account = visitor.get("/account")
    assert BANNER not in account.text
    assert "(verified)" in account.text

    again = visitor.post("/verify", data={"csrf_token": csrf_of(page.text), "token": token})
    assert "not valid" in again.text


def test_a_link_opened_logged_out_works_with_the_form_cookie(
    client: TestClient, settings: Settings
) -> None:
    register(browser(client))
    _, token = link_in(mails_to(settings, "alice@example.org")[0])
    elsewhere = browser(client)  # another browser, logged out
    page = elsewhere.get(f"/verify?token={token}")
    refused = elsewhere.post("/verify", data={"token": token})  # no form token
    assert refused.status_code == 403
    done = elsewhere.post("/verify", data={"csrf_token": csrf_of(page.text), "token": token})
    assert "is verified" in done.text


def test_the_banner_button_sends_a_new_link(client: TestClient, settings: Settings) -> None:
    visitor = browser(client)
    register(visitor)
    token = csrf_of(visitor.get("/account").text)
    r = visitor.post("/account/verify", data={"csrf_token": token})
    assert r.status_code == 303
    assert "We sent a new link" in visitor.get(r.headers["location"]).text
    assert len(mails_to(settings, "alice@example.org")) == 2


def test_forgot_password_answers_the_same_for_any_address_and_the_link_resets_once(
    client: TestClient, settings: Settings, db: Session
) -> None:
    make_user(db, "bob")
    visitor = browser(client)
    login_page = visitor.get("/login")
    assert 'href="/forgot-password"' in login_page.text

    def ask(email: str) -> str:
        token = csrf_of(visitor.get("/forgot-password").text)
        r = visitor.post("/forgot-password", data={"csrf_token": token, "email": email})
        assert r.status_code == 200
        return str(r.text)

    known, unknown = ask("bob@example.org"), ask("nobody@example.org")
    assert known.replace("bob@example.org", "X") == unknown.replace("nobody@example.org", "X")
    assert "we sent it a link" in known
    assert mails_to(settings, "nobody@example.org") == []
    path, token = link_in(mails_to(settings, "bob@example.org")[0])
    assert path == "/reset-password"

    form = visitor.get(f"/reset-password?token={token}")
    assert 'name="password"' in form.text
    csrf = csrf_of(form.text)
    weak = visitor.post(
        "/reset-password", data={"csrf_token": csrf, "token": token, "password": "abcdefghij"}
    )
    assert "too easy to guess" in weak.text
    assert 'name="password"' in weak.text  # the link still works
    done = visitor.post(
        "/reset-password", data={"csrf_token": csrf, "token": token, "password": NEW_PASSWORD}
    )
    assert done.status_code == 303
    assert done.headers["location"] == "/login?done=reset"
    assert "Your password is changed" in visitor.get(done.headers["location"]).text
    login = csrf_of(visitor.get("/login").text)
    r = visitor.post("/login", data={"csrf_token": login, "login": "bob", "password": NEW_PASSWORD})
    assert r.status_code == 303
    used = browser(client).get(f"/reset-password?token={token}")
    assert "not valid" in used.text
    assert 'name="password"' not in used.text


def test_an_expired_reset_link_shows_how_to_get_another(
    client: TestClient, settings: Settings, db: Session
) -> None:
    make_user(db, "cyd")
    visitor = browser(client)
    token = csrf_of(visitor.get("/forgot-password").text)
    visitor.post("/forgot-password", data={"csrf_token": token, "email": "cyd@example.org"})
    _, link = link_in(mails_to(settings, "cyd@example.org")[0])
    db.execute(update(EmailToken).values(expires_at=datetime.now(UTC) - timedelta(seconds=1)))
    db.commit()
    page = visitor.get(f"/reset-password?token={link}")
    assert "not valid" in page.text
    assert 'href="/forgot-password"' in page.text


def test_changing_the_address_on_the_account_page_reverifies(
    client: TestClient, settings: Settings, db: Session
) -> None:
    make_user(db, "dan")
    dan = browser(client, "dan")
    token = csrf_of(dan.get("/account").text)
    wrong = dan.post(
        "/account/email",
        data={"csrf_token": token, "email": "dan@new.example", "current_password": "nope nope"},
    )
    assert 'id="current_password-error"' in wrong.text
    assert mails_to(settings, "dan@new.example") == []
    ok = dan.post(
        "/account/email",
        data={"csrf_token": token, "email": "dan@new.example", "current_password": PASSWORD},
    )
    assert "We sent a link to dan@new.example" in ok.text
    assert "dan@example.org" in ok.text  # the account keeps its address until the link
    _, link = link_in(mails_to(settings, "dan@new.example")[0])
    page = dan.get(f"/verify?token={link}")
    dan.post("/verify", data={"csrf_token": csrf_of(page.text), "token": link})
    account = dan.get("/account").text
    assert "dan@new.example" in account
    assert "(verified)" in account


def test_an_unverified_account_cannot_submit_when_the_server_requires_it(
    client: TestClient, settings: Settings, db: Session
) -> None:
    make_challenge(db)
    app: Any = client.app
    app.state.services.settings = settings.model_copy(update={"require_verified_email": True})
    make_user(db, "eve", verified=False)
    eve = browser(client, "eve")
    form = eve.get("/challenges/server-tiny/submit")
    r = eve.post(
        "/challenges/server-tiny/submit",
        data={
            "csrf_token": csrf_of(form.text),
            "phase": "dev",
            "image": "127.0.0.1:5000/eve/policy:v1",
            "visibility": "public",
        },
    )
    assert r.status_code == 200  # the form again, with the reason
    assert "verify your email address before submitting" in r.text
