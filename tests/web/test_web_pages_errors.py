"""What people meet when something is refused: error pages that keep the navigation, a
logout link that asks first, readable problems with query parameters, and rejected forms that
a browser does not log as errors."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server.accounts import service as accounts
from server.app import create_app
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from server.models import Challenge
from testkit.factories import PASSWORD, RecordingQueue, make_user
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium, serving
from tests.web.helpers import browser, csrf_of


def nav_links(html: str) -> list[str]:
    nav = re.search(r'<nav class="site-nav".*?</nav>', html, re.DOTALL)
    assert nav, html
    return re.findall(r">([^<>]+)</(?:a|button)>", nav.group(0))


def test_an_error_page_keeps_log_in_and_register_for_visitors(client: TestClient) -> None:
    r = client.get("/submissions/12345")
    assert r.status_code == 404
    assert nav_links(r.text) == ["ManiEval", "Challenges", "Log in", "Register", "API"]


def test_an_error_page_keeps_the_navigation_of_someone_signed_in(
    client: TestClient, db: Session
) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    for r in (alice.get("/submissions/12345"), alice.get("/team/leave")):  # a 404, a 405
        assert r.status_code in (404, 405)
        assert nav_links(r.text) == [
            "ManiEval",
            "Challenges",
            "My submissions",
            "Team",
            "Account (alice)",
            "Log out",
            "API",
        ]
    stale = browser(client)  # the database says who it is: no one
    stale.cookies.set("manieval_session", "session_forged_or_expired")
    r = stale.get("/submissions/12345")
    assert nav_links(r.text) == ["ManiEval", "Challenges", "Log in", "Register", "API"]


def test_a_reload_of_the_new_token_page_as_a_get_is_the_account_page(
    client: TestClient, db: Session
) -> None:
    make_user(db, "alice")
    r = browser(client, "alice").get("/account/tokens")
    assert (r.status_code, r.headers["location"]) == (303, "/account#tokens")


def test_logout_by_link_asks_first_and_the_form_logs_out(client: TestClient, db: Session) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    page = alice.get("/logout")
    assert page.status_code == 200
    assert "Log out alice from this browser?" in page.text
    assert alice.get("/account").status_code == 200  # the link alone changed nothing
    done = alice.post("/logout", data={"csrf_token": csrf_of(page.text)})
    assert (done.status_code, done.headers["location"]) == (303, "/")
    assert alice.get("/account").status_code == 303  # to the login page
    visitor = browser(client).get("/logout")
    assert (visitor.status_code, "You are not logged in." in visitor.text) == (200, True)


def test_a_bad_query_parameter_is_explained_not_quoted_as_a_pattern(
    client: TestClient, tiny: Challenge
) -> None:
    r = client.get("/challenges/server-tiny/leaderboard?phase=dev&dir=sideways")
    assert r.status_code == 422
    assert "<strong>dir</strong>: must be one of: asc, desc" in r.text


@pytest.fixture
def served(tmp_path: Path) -> Iterator[str]:
    settings = Settings(dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False)
    settings.data_dir.mkdir(parents=True)
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        accounts.register(db, username="alice", email="alice@example.org", password=PASSWORD)
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield url


def test_rejected_forms_come_back_with_their_problems_and_no_console_error(served: str) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(chromium.new_page(viewport={"width": 1280, "height": 900}))
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))
        page.goto(f"{served}/register")
        page.fill("#username", "bob")
        page.fill("#email", "bob@example.org")
        page.fill("#password", "passwordpassword")
        page.click("main form button[type=submit]")
        expect(page.locator("#password-error")).to_be_visible(timeout=60_000)
        page.goto(f"{served}/login")
        page.fill("#login", "alice")
        page.fill("#password", "not the password")
        page.click("main form button[type=submit]")
        expect(page.get_by_text("Wrong username, email or password.")).to_be_visible(timeout=60_000)
        page.goto(f"{served}/logout")
        expect(page.get_by_text("You are not logged in.")).to_be_visible(timeout=60_000)
        chromium.close()
    assert problems == [], problems
