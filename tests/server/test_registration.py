"""Registration over the API forgives typos: rejected forms do not spend the per-address limit,
every problem comes in one answer, and user names are one account whatever their case."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from server.accounts import service as accounts
from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import User
from testkit.factories import PASSWORD, RecordingQueue, fake_resolve_for, make_user

API = "/api/v1"


def body(username: str = "dora", **overrides: str) -> dict[str, str]:
    return {"username": username, "email": f"{username}@example.org", "password": PASSWORD} | (
        overrides
    )


def limited_client(tmp_path: Path, sessions: sessionmaker[Session], **rates: str) -> TestClient:
    """The API with the default rate limits (or `rates`), counted in a fresh limiter."""
    settings = Settings(dev_mode=True, data_dir=tmp_path, cookie_secure=False, **rates)  # type: ignore[arg-type]
    app = create_app(
        settings,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    return TestClient(app)


@pytest.fixture
def defaults(tmp_path: Path, sessions: sessionmaker[Session]) -> Iterator[TestClient]:
    with limited_client(tmp_path, sessions) as client:
        yield client


def test_five_rejected_forms_then_a_correct_one_pass_the_default_limits(
    defaults: TestClient, db: Session
) -> None:
    make_user(db, "ada")
    rejected = [
        body(email="dora @example.org"),
        body(password="short"),
        body("Ada"),  # taken, whatever its case
        body("admin"),
        body(username="d", email="nowhere", password="passwordpassword"),
    ]
    answers = [defaults.post(f"{API}/users", json=form).status_code for form in rejected]
    assert answers == [422, 422, 409, 422, 422]
    assert defaults.post(f"{API}/users", json=body()).status_code == 201


def test_only_created_accounts_spend_the_register_rate(
    tmp_path: Path, sessions: sessionmaker[Session]
) -> None:
    with limited_client(tmp_path, sessions, register_rate="2/hour") as client:
        for _ in range(4):
            assert client.post(f"{API}/users", json=body(password="short")).status_code == 422
        assert client.post(f"{API}/users", json=body("jack")).status_code == 201
        assert client.post(f"{API}/users", json=body("jill")).status_code == 201
        refused = client.post(f"{API}/users", json=body(password="short"))
        assert refused.status_code == 429  # spent: refused before any check
        assert refused.json()["error"]["code"] == "rate_limited"


def test_every_attempt_counts_towards_the_login_rate(
    tmp_path: Path, sessions: sessionmaker[Session]
) -> None:
    with limited_client(tmp_path, sessions, login_rate="3/minute") as client:
        codes = [client.post(f"{API}/users", json=body("a")).status_code for _ in range(4)]
    assert codes == [422, 422, 422, 429]


def test_a_taken_address_spends_the_register_rate(
    tmp_path: Path, sessions: sessionmaker[Session], db: Session
) -> None:
    make_user(db, "ada")
    with limited_client(tmp_path, sessions, register_rate="1/hour") as client:
        probe = client.post(f"{API}/users", json=body("someone", email="ada@example.org"))
        assert probe.status_code == 409
        assert client.post(f"{API}/users", json=body()).status_code == 429


def test_every_problem_comes_in_one_answer_a_taken_name_among_them(
    client: TestClient, db: Session
) -> None:
    make_user(db, "dora")
    r = client.post(f"{API}/users", json=body("DORA", email="nowhere", password="short"))
    assert r.status_code == 422
    fields = r.json()["error"]["fields"]
    assert set(fields) == {"username", "email", "password"}
    assert fields["username"] == "already taken"


def test_a_taken_name_and_address_are_one_conflict(client: TestClient, db: Session) -> None:
    make_user(db, "dora")
    r = client.post(f"{API}/users", json=body("Dora"))
    assert r.status_code == 409
    error = r.json()["error"]
    assert error["fields"] == {"username": "already taken", "email": "already taken"}
    assert error["message"] == "this username and email are already registered"


def test_a_name_keeps_its_case_and_logs_in_whatever_the_case(client: TestClient) -> None:
    assert client.post(f"{API}/users", json=body("Dora")).json()["username"] == "Dora"
    for login in ("dora", "DORA", " Dora "):
        r = client.post(f"{API}/session", json={"login": login, "password": PASSWORD})
        assert r.status_code == 200, login
        assert r.json()["user"]["username"] == "Dora"
    again = client.post(f"{API}/users", json=body("dora", email="other@example.org"))
    assert again.status_code == 409
    assert again.json()["error"]["fields"] == {"username": "already taken"}


def test_the_database_refuses_names_differing_only_in_case(db: Session) -> None:
    make_user(db, "dora")
    db.add(User(username="Dora", email="d2@example.org", password_hash="x"))
    with pytest.raises(IntegrityError):
        db.flush()


def test_blanks_around_an_address_are_trimmed_and_inside_it_explained(client: TestClient) -> None:
    created = client.post(f"{API}/users", json=body(email="  dora@Example.org \n"))
    assert created.status_code == 201
    assert created.json()["email"] == "dora@example.org"
    r = client.post(f"{API}/users", json=body("eve", email="eve @example.org"))
    assert r.status_code == 422
    assert r.json()["error"]["fields"] == {"email": "an email address cannot contain spaces"}


def test_a_user_is_found_by_name_whatever_its_case(db: Session) -> None:
    dora = make_user(db, "Dora")
    assert accounts.user_named(db, username="dORA") is dora
    assert accounts.find_account(db, login="DORA") is dora
