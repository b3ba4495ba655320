"""Accounts over the API: registration rules, sessions with CSRF, API tokens, rate limits."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import ApiToken
from testkit.factories import PASSWORD, RecordingQueue, fake_resolve_for, token_for

API = "/api/v1"


def register(client: TestClient, username: str, **overrides: str) -> dict[str, object]:
    body = {"username": username, "email": f"{username}@example.org", "password": PASSWORD}
    body.update(overrides)
    r = client.post(f"{API}/users", json=body)
    return {"status": r.status_code, **r.json()}


def test_register_then_login_with_cookie(client: TestClient) -> None:
    assert register(client, "alice")["status"] == 201
    r = client.post(f"{API}/session", json={"login": "alice", "password": PASSWORD})
    assert r.status_code == 200
    assert "manieval_session" in r.cookies
    assert "httponly" in r.headers["set-cookie"].lower()
    me = client.get(f"{API}/me").json()
    assert me["user"]["username"] == "alice"
    assert me["csrf_token"] == r.json()["csrf_token"]


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"username": "Al"}, "username"),
        ({"username": "admin"}, "username"),
        ({"email": "not-an-email"}, "email"),
        ({"password": "short"}, "password"),
        ({"password": "password123456"}, "password"),
        ({"password": "bob-the-builder-bob"}, "password"),
    ],
)
def test_register_rejects_bad_input_with_field_errors(
    client: TestClient, overrides: dict[str, str], field: str
) -> None:
    rest = dict(overrides)
    out = register(client, rest.pop("username", "bob-the-builder"), **rest)
    assert out["status"] == 422
    error = out["error"]
    assert isinstance(error, dict)
    assert field in error["fields"], error


def test_register_twice_is_a_conflict(client: TestClient) -> None:
    register(client, "carol")
    again = register(client, "carol", email="other@example.org")
    assert again["status"] == 409
    same_email = register(client, "carol2", email="CAROL@example.org")
    assert same_email["status"] == 409


def test_wrong_password_is_401_and_says_nothing_more(client: TestClient) -> None:
    register(client, "dave")
    for login in ("dave", "nobody"):
        r = client.post(f"{API}/session", json={"login": login, "password": "wrong" * 4})
        assert r.status_code == 401
        assert r.json()["error"]["message"] == "wrong username, email or password"


def test_cookie_writes_need_the_csrf_token(client: TestClient) -> None:
    register(client, "erin")
    csrf = client.post(f"{API}/session", json={"login": "erin", "password": PASSWORD}).json()[
        "csrf_token"
    ]
    refused = client.post(f"{API}/tokens", json={"name": "laptop"})
    assert refused.status_code == 403
    assert "CSRF" in refused.json()["error"]["message"]
    wrong = client.post(f"{API}/tokens", json={"name": "laptop"}, headers={"X-CSRF-Token": "x"})
    assert wrong.status_code == 403
    ok = client.post(f"{API}/tokens", json={"name": "laptop"}, headers={"X-CSRF-Token": csrf})
    assert ok.status_code == 201


def test_token_shown_once_stored_hashed_and_revocable(
    client: TestClient, sessions: sessionmaker[Session]
) -> None:
    register(client, "frank")
    headers = token_for(client, "frank")
    created = client.post(f"{API}/tokens", json={"name": "ci"}, headers=headers)
    assert created.status_code == 201
    plaintext = created.json()["token"]
    assert plaintext.startswith("mev_")
    listed = client.get(f"{API}/tokens", headers=headers).json()
    assert all("token" not in t for t in listed)
    with sessions() as db:
        stored = db.get(ApiToken, created.json()["id"])
        assert stored is not None
        assert plaintext not in (stored.digest, stored.prefix)
    new = {"Authorization": f"Bearer {plaintext}"}
    assert client.get(f"{API}/me", headers=new).status_code == 200
    assert client.get(f"{API}/tokens", headers=headers).json()[0]["last_used_at"] is not None
    revoked = client.delete(f"{API}/tokens/{created.json()['id']}", headers=headers)
    assert revoked.status_code == 200
    assert client.get(f"{API}/me", headers=new).status_code == 401


def test_cannot_revoke_someone_elses_token(client: TestClient) -> None:
    register(client, "gina")
    register(client, "hank")
    gina, hank = token_for(client, "gina"), token_for(client, "hank")
    token_id = client.get(f"{API}/tokens", headers=gina).json()[0]["id"]
    assert client.delete(f"{API}/tokens/{token_id}", headers=hank).status_code == 404
    assert client.get(f"{API}/me", headers=gina).status_code == 200


@pytest.mark.parametrize(
    "header", ["Bearer mev_nope", "Basic Zm9vOmJhcg==", "Bearer", "Bearer mev_" + "A" * 60]
)
def test_malformed_authorization_is_401(client: TestClient, header: str) -> None:
    r = client.get(f"{API}/me", headers={"Authorization": header})
    assert r.status_code == 401
    assert r.json()["error"]["code"] == "unauthorized"


def test_logout_ends_the_session(client: TestClient) -> None:
    register(client, "ivan")
    csrf = client.post(f"{API}/session", json={"login": "ivan", "password": PASSWORD}).json()[
        "csrf_token"
    ]
    assert client.delete(f"{API}/session", headers={"X-CSRF-Token": csrf}).status_code == 200
    assert client.get(f"{API}/me").status_code == 401


def test_rate_limits_answer_429_with_retry_after(
    tmp_path: object, sessions: sessionmaker[Session]
) -> None:
    settings = Settings(
        dev_mode=True,
        data_dir=tmp_path,
        cookie_secure=False,
        register_rate="2/hour",
        login_rate="3/minute",
    )
    app = create_app(
        settings,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for,
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app) as client:
        assert register(client, "jack")["status"] == 201
        assert register(client, "jill")["status"] == 201
        third = client.post(
            f"{API}/users",
            json={"username": "joan", "email": "joan@example.org", "password": PASSWORD},
        )
        assert third.status_code == 429
        assert int(third.headers["Retry-After"]) > 0
        assert third.json()["error"]["code"] == "rate_limited"
        codes = [
            client.post(f"{API}/session", json={"login": "jack", "password": "x" * 12}).status_code
            for _ in range(4)
        ]
        assert codes == [401, 401, 401, 429]
