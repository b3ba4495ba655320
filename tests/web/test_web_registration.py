"""The register form forgives typos: rejected forms do not spend the limit, every problem is
shown at once with the other fields kept, and the fields do not let a phone change the name."""

from __future__ import annotations

import re
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from testkit.factories import PASSWORD, RecordingQueue, fake_resolve_for, make_user
from tests.web.helpers import browser, csrf_of

NO_PHONE_CHANGES = ('autocapitalize="none"', 'autocorrect="off"', 'spellcheck="false"')


def register(client: TestClient, **fields: str) -> object:
    form = {"username": "dora", "email": "dora@example.org", "password": PASSWORD} | fields
    token = csrf_of(client.get("/register").text)
    return client.post("/register", data={"csrf_token": token, **form})


def errors_of(html: str) -> dict[str, str]:
    return dict(re.findall(r'<p class="field-error" id="([a-z_]+)-error">([^<]*)</p>', html))


def test_five_rejected_forms_then_a_correct_one_pass_the_default_limits(
    tmp_path: Path, sessions: sessionmaker[Session], db: Session
) -> None:
    make_user(db, "ada")
    settings = Settings(dev_mode=True, data_dir=tmp_path, cookie_secure=False)
    app = create_app(
        settings,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app, base_url="http://testserver", follow_redirects=False) as visitor:
        for fields in [
            {"email": "dora @example.org"},
            {"password": "short"},
            {"username": "Ada"},
            {"username": "admin"},
            {"username": "d", "email": "nowhere", "password": "passwordpassword"},
        ]:
            r = register(visitor, **fields)
            assert r.status_code == 200, fields  # type: ignore[attr-defined]
            assert errors_of(r.text), fields  # type: ignore[attr-defined]
            assert "too many" not in r.text  # type: ignore[attr-defined]
        done = register(visitor)
        assert done.status_code == 303  # type: ignore[attr-defined]
        assert "dora@example.org" in visitor.get("/account").text


def test_every_problem_is_shown_at_once_and_the_other_fields_are_kept(
    client: TestClient, db: Session
) -> None:
    make_user(db, "dora")
    r = register(browser(client), username="Dora", email="dora @example.org", password="short")
    html = r.text  # type: ignore[attr-defined]
    assert errors_of(html) == {
        "username": "already taken",
        "email": "an email address cannot contain spaces",
        "password": "Use at least 10 characters.",
    }
    assert 'value="Dora"' in html
    assert 'value="dora @example.org"' in html
    # The password is never sent back: the form says so instead of silently emptying it.
    assert 'id="password-again">Enter your password again:' in html
    assert re.search(r'id="password"[^>]*aria-describedby="password-hint', html)
    assert not re.search(r'id="password"[^>]*value=', html)


def test_a_registered_name_keeps_its_case_and_logs_in_in_any_case(client: TestClient) -> None:
    assert register(browser(client), username="Dora").status_code == 303  # type: ignore[attr-defined]
    visitor = browser(client)
    token = csrf_of(visitor.get("/login").text)
    r = visitor.post("/login", data={"csrf_token": token, "login": "dora", "password": PASSWORD})
    assert r.status_code == 303
    assert "<dd>Dora</dd>" in visitor.get("/account").text


def test_name_and_address_fields_let_no_phone_change_them(client: TestClient) -> None:
    pages = {
        "/register": ['id="username"', 'id="email"'],
        "/login": ['id="login"'],
        "/forgot-password": ['id="email"'],
    }
    for path, inputs in pages.items():
        html = client.get(path).text
        for input_id in inputs:
            tag = re.search(rf"<input {input_id}[^>]*>", html)
            assert tag, (path, input_id)
            assert all(attribute in tag.group(0) for attribute in NO_PHONE_CHANGES), tag.group(0)
    register_page = client.get("/register").text
    assert re.search(r'id="username"[^>]*autocomplete="username"', register_page)
    assert re.search(r'id="email"[^>]*autocomplete="email"', register_page)
    assert re.search(r'id="password"[^>]*autocomplete="new-password"', register_page)
