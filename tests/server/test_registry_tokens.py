"""The token service of the service's own registry, without a registry: the signing key, the
registry config, the scope rules, and ``GET /registry/token`` (tests/server/test_registry_auth.py
runs the same against a real registry)."""

from __future__ import annotations

import base64
import stat
from collections.abc import Iterator
from pathlib import Path

import jwt
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from fastapi.testclient import TestClient
from pydantic import SecretStr, ValidationError
from sqlalchemy.orm import Session, sessionmaker

from server.accounts import service as accounts
from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.security import RESERVED_USERNAMES
from server.kit.settings import Settings
from server.models import User
from server.registry.config import registry_config
from server.registry.keys import SigningKeyMissing, ensure_signing_key, load_signing_key
from server.registry.service import publish_token
from server.registry.tokens import (
    SERVICE_NAMESPACE,
    Access,
    Grantee,
    grant,
    namespace_for,
    parse_scopes,
)
from testkit.factories import RecordingQueue, fake_resolve_for, make_user

PULL_PASSWORD = "pull-" + "q" * 40


def basic(user: str, password: str) -> dict[str, str]:
    return {"Authorization": "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()}


# The key and the registry's configuration ----------------------------------------------------


def test_signing_key_is_made_once_private_and_then_reused(tmp_path: Path) -> None:
    with pytest.raises(SigningKeyMissing):
        load_signing_key(tmp_path / "key")
    first = ensure_signing_key(tmp_path / "key")
    assert stat.S_IMODE(first.key_path.stat().st_mode) == 0o600
    again = ensure_signing_key(tmp_path / "key")
    assert again.private_pem() == first.private_pem()
    assert again.cert_path.read_bytes() == first.cert_path.read_bytes()
    assert first.algorithm() == "ES256"
    cert = x509.load_pem_x509_certificate(first.cert_path.read_bytes())
    assert base64.b64decode(first.x5c()[0]) == cert.public_bytes(serialization.Encoding.DER)


def test_registry_config_uses_token_auth_against_the_server(tmp_path: Path) -> None:
    config = registry_config(
        addr="127.0.0.1:5000",
        storage=tmp_path / "storage",
        realm="http://127.0.0.1:8000/registry/token",
        cert_path=tmp_path / "tls.crt",
        service="svc",
        issuer="iss",
    )
    assert config["auth"] == {
        "token": {
            "realm": "http://127.0.0.1:8000/registry/token",
            "service": "svc",
            "issuer": "iss",
            "rootcertbundle": str(tmp_path / "tls.crt"),
        }
    }
    assert config["storage"]["filesystem"] == {"rootdirectory": str(tmp_path / "storage")}
    assert config["storage"]["delete"] == {"enabled": True}
    assert config["http"]["addr"] == "127.0.0.1:5000"
    assert "secret" not in config["http"]


# Scopes ------------------------------------------------------------------------------------------

ALICE = Grantee(subject="alice", namespace="alice")
PULLER = Grantee(subject="manieval-puller", namespace=None, pull_anywhere=True)


@pytest.mark.parametrize(
    ("scopes", "grantee", "granted"),
    [
        (["repository:alice/policy:push,pull"], ALICE, [("alice/policy", ("pull", "push"))]),
        (["repository:alice/a/b:pull"], ALICE, [("alice/a/b", ("pull",))]),
        (["repository:bob/policy:push,pull"], ALICE, []),
        (["repository:alicex/policy:pull"], ALICE, []),
        (["repository:alice:pull"], ALICE, [("alice", ("pull",))]),
        (["repository:alice/policy:*"], ALICE, []),  # delete and the rest: nobody
        (["repository:alice/Policy:pull"], ALICE, []),  # not a repository name
        (["repository:alice/../x:pull"], ALICE, []),
        (["registry:catalog:*"], ALICE, []),
        (["repository(plugin):alice/p:pull"], ALICE, [("alice/p", ("pull",))]),
        (["repository:bob/policy:push,pull"], PULLER, [("bob/policy", ("pull",))]),
        (["registry:catalog:*"], PULLER, []),
        (
            ["repository:alice/p:pull repository:bob/q:pull", "repository:alice/p:push"],
            ALICE,
            [("alice/p", ("pull", "push"))],
        ),
        (["nonsense", "repository::pull", ""], ALICE, []),
        # The service's own images (the policy base): everyone pulls, nobody pushes.
        (
            ["repository:manieval/policy-base:pull,push"],
            ALICE,
            [("manieval/policy-base", ("pull",))],
        ),
        (["repository:manieval/policy-base:push"], ALICE, []),
        (
            ["repository:manieval/policy-base:pull,push"],
            PULLER,
            [("manieval/policy-base", ("pull",))],
        ),
        (["repository:manievalx/policy-base:pull"], ALICE, []),
        # ... even for an account that held the name (it is reserved): the rule comes first
        (["repository:manieval/x:push"], Grantee(subject="manieval", namespace="manieval"), []),
    ],
)
def test_scopes_are_granted_only_within_the_callers_rights(
    scopes: list[str], grantee: Grantee, granted: list[tuple[str, tuple[str, ...]]]
) -> None:
    expected = [Access(type="repository", name=n, actions=a) for n, a in granted]
    assert grant(parse_scopes(scopes), grantee) == expected


def test_scope_lists_are_bounded() -> None:
    assert len(parse_scopes([f"repository:alice/p{i}:pull" for i in range(100)])) == 16


@pytest.mark.parametrize(
    ("username", "namespace"),
    [("alice", "alice"), ("bob-2", "bob-2"), ("a_b", "a_b"), ("bob_", None), ("x-", None)],
)
def test_namespace_is_the_user_name_when_it_is_a_path_component(
    username: str, namespace: str | None
) -> None:
    assert namespace_for(username) == namespace


def test_no_account_can_own_the_services_namespace() -> None:
    assert SERVICE_NAMESPACE in RESERVED_USERNAMES


@pytest.mark.parametrize(
    "repository", ["alice/policy", "manieval", "manieval/Base", "x/manieval/a"]
)
def test_the_server_publishes_only_under_its_own_namespace(tmp_path: Path, repository: str) -> None:
    settings = Settings(dev_mode=True, data_dir=tmp_path, registry_domain="127.0.0.1:5000")
    with pytest.raises(ValueError, match="publishes only under manieval/"):
        publish_token(settings, repository=repository)
    token = publish_token(settings, repository="manieval/policy-base")
    claims = jwt.decode(token, options={"verify_signature": False})
    assert claims["access"] == [
        {"type": "repository", "name": "manieval/policy-base", "actions": ["pull", "push"]}
    ]


# Settings --------------------------------------------------------------------------------------


def test_production_with_a_registry_needs_a_pull_password(tmp_path: Path) -> None:
    strong = dict.fromkeys(("secret_key", "seed_secret", "worker_token"), "s" * 32)
    with pytest.raises(ValidationError, match="MANIEVAL_REGISTRY_PULL_PASSWORD"):
        Settings(data_dir=tmp_path, registry_domain="registry.example.org", **strong)  # type: ignore[arg-type]
    Settings(data_dir=tmp_path, **strong)  # type: ignore[arg-type]
    Settings(
        data_dir=tmp_path,
        registry_domain="registry.example.org",
        registry_pull_password=PULL_PASSWORD,  # type: ignore[arg-type]
        **strong,  # type: ignore[arg-type]
    )


def test_dev_mode_generates_and_keeps_the_pull_password(tmp_path: Path) -> None:
    settings = Settings(dev_mode=True, data_dir=tmp_path, registry_domain="127.0.0.1:5000")
    generated = settings.secret("registry_pull_password")
    assert len(generated) >= 32
    again = Settings(dev_mode=True, data_dir=tmp_path, registry_domain="127.0.0.1:5000")
    assert again.secret("registry_pull_password") == generated


# The endpoint ----------------------------------------------------------------------------------


def token_client(
    settings: Settings, sessions: sessionmaker[Session], **overrides: object
) -> TestClient:
    configured = settings.model_copy(
        update={
            "registry_domain": "127.0.0.1:5000",
            "registry_pull_password": SecretStr(PULL_PASSWORD),
            **overrides,
        }
    )
    app = create_app(
        configured,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(configured),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    return TestClient(app)


@pytest.fixture
def alice_token(sessions: sessionmaker[Session]) -> str:
    with sessions() as db:
        user = make_user(db, "alice")
        plaintext = accounts.create_token(db, user=user, name="registry")[1]
        db.commit()
    return plaintext


@pytest.fixture
def tokens(settings: Settings, sessions: sessionmaker[Session]) -> Iterator[TestClient]:
    with token_client(settings, sessions) as client:
        yield client


def test_token_answer_follows_the_specification_and_verifies(
    tokens: TestClient, settings: Settings, alice_token: str
) -> None:
    r = tokens.get(
        "/registry/token",
        params={"service": "manieval-registry", "scope": "repository:alice/policy:pull,push"},
        headers=basic("alice", alice_token),
    )
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["token"] == answer["access_token"]
    assert answer["expires_in"] == 300
    assert answer["issued_at"].endswith("Z") or "+00:00" in answer["issued_at"]
    header = jwt.get_unverified_header(answer["token"])
    assert header["alg"] == "ES256"
    cert = x509.load_der_x509_certificate(base64.b64decode(header["x5c"][0]))
    claims = jwt.decode(
        answer["token"],
        cert.public_key(),  # type: ignore[arg-type]
        algorithms=["ES256"],
        audience="manieval-registry",
        issuer="manieval",
    )
    assert claims["sub"] == "alice"
    assert claims["exp"] - claims["iat"] == 300
    assert claims["access"] == [
        {"type": "repository", "name": "alice/policy", "actions": ["pull", "push"]}
    ]
    key = ensure_signing_key(settings.data_dir / "registry-key")
    assert key.x5c() == header["x5c"]


def test_login_without_scope_gets_a_token_with_no_access(
    tokens: TestClient, alice_token: str
) -> None:
    r = tokens.get("/registry/token", headers=basic("alice", alice_token))
    assert r.status_code == 200
    assert jwt.decode(r.json()["token"], options={"verify_signature": False})["access"] == []


@pytest.mark.parametrize(
    "headers",
    [
        {},
        {"Authorization": "Bearer something"},
        {"Authorization": "Basic !!!"},
        basic("alice", "not-a-token"),
        basic("alice", ""),
        basic("manieval-puller", "wrong"),
    ],
)
def test_no_token_without_valid_credentials(
    tokens: TestClient, alice_token: str, headers: dict[str, str]
) -> None:
    r = tokens.get("/registry/token", params={"scope": "repository:alice/p:pull"}, headers=headers)
    assert r.status_code == 401
    assert r.headers["WWW-Authenticate"].startswith('Basic realm="manieval-registry"')
    assert '"token"' not in r.text


def test_api_token_of_another_user_name_is_refused(
    tokens: TestClient, sessions: sessionmaker[Session], alice_token: str
) -> None:
    with sessions() as db:
        make_user(db, "bob")
    assert tokens.get("/registry/token", headers=basic("bob", alice_token)).status_code == 401
    assert tokens.get("/registry/token", headers=basic("ALICE", alice_token)).status_code == 200


def test_revoked_api_token_gets_no_registry_token(
    tokens: TestClient, sessions: sessionmaker[Session], alice_token: str
) -> None:
    assert tokens.get("/registry/token", headers=basic("alice", alice_token)).status_code == 200
    with sessions() as db:
        alice = db.query(User).filter_by(username="alice").one()
        for token in accounts.list_tokens(db, user=alice):
            accounts.revoke_token(db, user=alice, token_id=token.id)
        db.commit()
    assert tokens.get("/registry/token", headers=basic("alice", alice_token)).status_code == 401


def test_pull_credential_gets_pull_anywhere(tokens: TestClient) -> None:
    r = tokens.get(
        "/registry/token",
        params={"scope": "repository:alice/policy:pull,push"},
        headers=basic("manieval-puller", PULL_PASSWORD),
    )
    assert r.status_code == 200
    access = jwt.decode(r.json()["token"], options={"verify_signature": False})["access"]
    assert access == [{"type": "repository", "name": "alice/policy", "actions": ["pull"]}]


def test_tokens_for_another_service_are_refused(tokens: TestClient, alice_token: str) -> None:
    r = tokens.get(
        "/registry/token", params={"service": "other"}, headers=basic("alice", alice_token)
    )
    assert r.status_code == 422


def test_service_without_a_registry_has_no_token_endpoint(
    settings: Settings, sessions: sessionmaker[Session], alice_token: str
) -> None:
    with token_client(settings, sessions, registry_domain=None) as client:
        r = client.get("/registry/token", headers=basic("alice", alice_token))
    assert r.status_code == 404


def test_token_requests_are_rate_limited_per_address_and_user_name(
    settings: Settings, sessions: sessionmaker[Session], alice_token: str
) -> None:
    with token_client(settings, sessions, registry_token_rate="3/minute") as client:
        answers = [
            client.get("/registry/token", headers=basic("alice", f"guess{i}")).status_code
            for i in range(5)
        ]
        assert answers == [401, 401, 401, 429, 429]
        limited = client.get("/registry/token", headers=basic("alice", alice_token))
    assert limited.status_code == 429  # even the right token, until the window passes
    assert int(limited.headers["Retry-After"]) >= 1


def test_a_missing_signing_key_is_unavailable_not_a_crash(
    settings: Settings, sessions: sessionmaker[Session], alice_token: str, tmp_path: Path
) -> None:
    with token_client(settings, sessions, registry_key_dir=tmp_path / "absent") as client:
        r = client.get("/registry/token", headers=basic("alice", alice_token))
    assert r.status_code == 503
    assert "registry signing key is missing" in r.text
