"""The service's own registry against a real one: Debian's docker-registry configured by
``registry_config``, sending clients for tokens to a real ManiEval server (uvicorn on a free
port) that signs them. Each test makes a client's requests to the registry, as podman or docker
make them, and asserts what the registry itself answers.
"""

from __future__ import annotations

import datetime as dt
import io
import os
import subprocess
import tarfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import jwt
import pytest
import uvicorn
from sqlalchemy.orm import Session, sessionmaker

from server.accounts import service as accounts
from server.app import create_app
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.errors import AppError
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import User
from server.registry import service as registry
from server.registry.config import TOKEN_PATH, registry_config
from server.registry.tokens import Access
from server.submissions.images import image_resolver
from testkit.factories import RecordingQueue, make_challenge, make_user
from tests.server.registry_fixture import (
    REGISTRY_BINARY,
    RegistryLogin,
    free_port,
    push_image,
    require_tool,
    serve_registry_config,
)

PULL_PASSWORD = "pull-" + "p" * 40
ACCEPT = {"Accept": "application/vnd.oci.image.manifest.v1+json"}


@dataclass
class Stack:
    settings: Settings
    sessions: sessionmaker[Session]
    server: str  # the ManiEval server's URL
    domain: str  # the registry's
    tokens: dict[str, str]  # user name -> API token

    def client(self, login: RegistryLogin | None = None) -> httpx.Client:
        return httpx.Client(base_url=f"http://{self.domain}", auth=login, timeout=30)

    def as_user(self, username: str, token: str | None = None) -> httpx.Client:
        return self.client(RegistryLogin(username, token or self.tokens[username]))

    def puller(self, password: str = PULL_PASSWORD) -> httpx.Client:
        return self.client(RegistryLogin(self.settings.registry_pull_user, password))

    def manifest(self, http: httpx.Client, repository: str, tag: str = "v1") -> httpx.Response:
        return http.get(f"/v2/{repository}/manifests/{tag}", headers=ACCEPT)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """docker-registry with the config the service writes, and the server that signs its
    tokens; users alice and bob, each with an API token, and alice/policy:v1 pushed."""
    binary = require_tool(REGISTRY_BINARY)
    work = tmp_path_factory.mktemp("own-registry")
    port = free_port()
    server = f"http://127.0.0.1:{port}"
    base = Settings(
        dev_mode=True,
        data_dir=work / "data",
        cookie_secure=False,
        registry_pull_password=PULL_PASSWORD,  # type: ignore[arg-type]
        registry_token_rate="10000/minute",
        login_rate="10000/minute",
    )
    key = registry.signing_key(base)

    def config(domain: str) -> dict[str, object]:
        return registry_config(
            addr=domain,
            storage=work / "storage",
            realm=f"{server}{TOKEN_PATH}",
            cert_path=key.cert_path,
            service=base.registry_service,
            issuer=base.registry_issuer,
        )

    with serve_registry_config(binary, work, config) as domain:
        settings = base.model_copy(update={"registry_domain": domain})
        url = f"sqlite:///{work / 'manieval.db'}"
        upgrade(url)
        sessions = session_factory(make_engine(url))
        tokens = {}
        with sessions() as db:
            make_challenge(db, quota_concurrent=10)
            for name in ("alice", "bob"):
                user = make_user(db, name)
                tokens[name] = accounts.create_token(db, user=user, name="registry")[1]
            db.commit()
        app = create_app(
            settings,
            sessions=sessions,
            work=RecordingQueue(),
            limiter=MemoryRateLimiter(),
            background=False,
        )
        with _serving(app, port):
            built = Stack(settings, sessions, server, domain, tokens)
            with built.as_user("alice") as http:
                push_image(http, "alice/policy", "v1", layer_sizes=[1000, 2000])
            yield built


class _serving:
    """uvicorn in a thread on ``port`` for the duration of a ``with``."""

    def __init__(self, app: object, port: int) -> None:
        # No log_config: uvicorn would reconfigure this process's logging for later tests.
        config = uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None)  # type: ignore[arg-type]
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="uvicorn", daemon=True)

    def __enter__(self) -> None:
        self._thread.start()
        while not self._server.started:
            assert self._thread.is_alive(), "the server did not start"
            time.sleep(0.02)

    def __exit__(self, *_: object) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=30)


def claims(token: str) -> dict[str, object]:
    """A token's claims, read without verifying (the registry verifies)."""
    decoded: dict[str, object] = jwt.decode(token, options={"verify_signature": False})
    return decoded


# The security properties ---------------------------------------------------------------------


def test_owner_pushes_and_pulls_in_their_namespace(stack: Stack) -> None:
    with stack.as_user("alice") as http:
        pushed = push_image(http, "alice/tools/other", "v2", layer_sizes=[500])
        got = stack.manifest(http, "alice/tools/other", "v2")
    assert got.status_code == 200, got.text
    assert got.headers["Docker-Content-Digest"] == pushed.digest


def test_another_users_namespace_refuses_push_and_pull(stack: Stack) -> None:
    login = RegistryLogin("bob", stack.tokens["bob"])
    with stack.client(login) as http:
        assert stack.manifest(http, "alice/policy").status_code == 401
        upload = http.post("/v2/alice/policy/blobs/uploads/")
        assert upload.status_code == 401
        assert upload.json()["errors"][0]["code"] == "UNAUTHORIZED"
    # bob did get tokens (he is a user), with nothing in them for alice's repository
    assert login.tokens
    assert all(claims(token)["access"] == [] for token in login.tokens)


def test_revoked_api_token_stops_working_for_the_registry(stack: Stack) -> None:
    with stack.sessions() as db:
        alice = db.query(User).filter_by(username="alice").one()
        token, plaintext = accounts.create_token(db, user=alice, name="to revoke")
        db.commit()
    with stack.as_user("alice", plaintext) as http:
        assert stack.manifest(http, "alice/policy").status_code == 200
    with stack.sessions() as db:
        accounts.revoke_token(db, user=alice, token_id=token.id)
        db.commit()
    login = RegistryLogin("alice", plaintext)
    with stack.client(login) as http:
        assert stack.manifest(http, "alice/policy").status_code == 401
    assert login.tokens == []
    assert [r.status_code for r in login.refusals] == [401]


def test_expired_registry_token_is_refused(stack: Stack) -> None:
    signer = registry.signer(stack.settings)
    access = [Access(type="repository", name="alice/policy", actions=("pull",))]
    past = dt.datetime.now(dt.UTC) - dt.timedelta(seconds=stack.settings.registry_token_ttl_s + 60)
    expired = signer.issue(subject="alice", access=access, now=past).token
    fresh = signer.issue(subject="alice", access=access).token
    with stack.client() as http:
        for token, status in ((expired, 401), (fresh, 200)):
            r = http.get(
                "/v2/alice/policy/manifests/v1",
                headers={**ACCEPT, "Authorization": f"Bearer {token}"},
            )
            assert r.status_code == status, r.text


def test_token_signed_by_another_key_is_refused(stack: Stack, tmp_path: Path) -> None:
    other = Settings(dev_mode=True, data_dir=tmp_path)
    access = [Access(type="repository", name="alice/policy", actions=("pull",))]
    forged = registry.signer(other).issue(subject="alice", access=access).token
    with stack.client() as http:
        r = http.get(
            "/v2/alice/policy/manifests/v1",
            headers={**ACCEPT, "Authorization": f"Bearer {forged}"},
        )
    assert r.status_code == 401
    registry.signer(stack.settings)  # the cache holds the service's key again


def test_anonymous_pull_is_refused_and_gets_no_token(stack: Stack) -> None:
    login = RegistryLogin()
    with stack.client(login) as http:
        assert stack.manifest(http, "alice/policy").status_code == 401
    assert login.tokens == []
    refusal = login.refusals[0]
    assert refusal.status_code == 401
    assert refusal.headers["WWW-Authenticate"].startswith("Basic ")


def test_token_for_one_repository_does_not_open_another(stack: Stack) -> None:
    login = RegistryLogin("alice", stack.tokens["alice"])
    with stack.client(login) as http:
        assert stack.manifest(http, "alice/policy").status_code == 200
    (token,) = login.tokens
    assert claims(token)["access"] == [
        {"type": "repository", "name": "alice/policy", "actions": ["pull"]}
    ]
    with stack.client() as http:
        for path in ("/v2/alice/tools/other/manifests/v2", "/v2/bob/policy/manifests/v1"):
            r = http.get(path, headers={**ACCEPT, "Authorization": f"Bearer {token}"})
            assert r.status_code == 401, path
        upload = http.post(
            "/v2/alice/policy/blobs/uploads/", headers={"Authorization": f"Bearer {token}"}
        )
        assert upload.status_code == 401  # a pull token does not push either


def test_pull_only_credential_pulls_anything_and_pushes_nothing(stack: Stack) -> None:
    with stack.puller() as http:
        assert stack.manifest(http, "alice/policy").status_code == 200
        assert http.post("/v2/alice/policy/blobs/uploads/").status_code == 401
        assert http.post("/v2/manieval-puller/x/blobs/uploads/").status_code == 401
    with stack.puller(password="wrong" * 8) as http:
        assert stack.manifest(http, "alice/policy").status_code == 401


def test_user_name_must_match_the_api_token(stack: Stack) -> None:
    login = RegistryLogin("bob", stack.tokens["alice"])
    with stack.client(login) as http:
        assert stack.manifest(http, "alice/policy").status_code == 401
    assert [r.status_code for r in login.refusals] == [401]


def test_catalog_is_not_granted_to_anyone(stack: Stack) -> None:
    for http in (stack.as_user("alice"), stack.puller()):
        with http:
            assert http.get("/v2/_catalog").status_code == 401


# The server's own use of its registry ----------------------------------------------------------


def test_server_pins_images_of_its_own_registry_with_a_token_it_signs(stack: Stack) -> None:
    resolve = image_resolver(stack.settings)
    with stack.as_user("alice") as http:
        digest = stack.manifest(http, "alice/policy").headers["Docker-Content-Digest"]
    resolved = resolve(f"{stack.domain}/alice/policy:v1", owner="alice")
    assert resolved.pinned == f"{stack.domain}/alice/policy@{digest}"
    assert resolved.size_bytes is not None
    assert resolved.size_bytes > 3000


def test_submitting_another_users_image_from_the_own_registry_is_refused(stack: Stack) -> None:
    resolve = image_resolver(stack.settings)
    with pytest.raises(AppError, match="must be under your namespace") as caught:
        resolve(f"{stack.domain}/alice/policy:v1", owner="bob")
    assert caught.value.status == 422


def test_submissions_through_the_api_pin_own_images_and_refuse_others(stack: Stack) -> None:
    image = f"{stack.domain}/alice/policy:v1"
    answers = {}
    for name in ("alice", "bob"):
        answers[name] = httpx.post(
            f"{stack.server}/api/v1/submissions",
            json={"challenge": "server-tiny", "image": image},
            headers={"Authorization": f"Bearer {stack.tokens[name]}"},
            timeout=30,
        )
    assert answers["alice"].status_code == 202, answers["alice"].text
    assert answers["alice"].json()["pinned_image"].startswith(f"{stack.domain}/alice/policy@")
    assert answers["bob"].status_code == 422
    assert "under your namespace" in answers["bob"].json()["error"]["fields"]["image"]


# The engine's path: podman login and push ------------------------------------------------------


def _tiny_image(podman: str, name: str) -> None:
    """A one-file image made by ``podman import`` (no base image, no network)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        data = b"manieval registry test\n"
        info = tarfile.TarInfo("hello.txt")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    subprocess.run(
        [podman, "import", "-", name], input=buffer.getvalue(), check=True, capture_output=True
    )


def podman_as_a_user(podman: str, home: Path) -> Callable[..., subprocess.CompletedProcess[str]]:
    """`podman ARGS` with a login file of its own in `home`, as one user's terminal."""
    env = {**os.environ, "REGISTRY_AUTH_FILE": str(home / "auth.json")}

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [podman, *args], env=env, capture_output=True, text=True, timeout=300, check=False
        )

    return run


def test_podman_login_and_push_work_in_the_own_namespace_only(stack: Stack, tmp_path: Path) -> None:
    podman = require_tool("podman")
    run = podman_as_a_user(podman, tmp_path)
    name = f"localhost/manieval-registry-test:{os.getpid()}"

    _tiny_image(podman, name)
    try:
        wrong = run("login", "--tls-verify=false", "-u", "alice", "-p", "nope", stack.domain)
        assert wrong.returncode != 0
        login = run(
            "login", "--tls-verify=false", "-u", "alice", "-p", stack.tokens["alice"], stack.domain
        )
        assert login.returncode == 0, login.stderr
        pushed = run("push", "--tls-verify=false", name, f"docker://{stack.domain}/alice/tiny:v1")
        assert pushed.returncode == 0, pushed.stderr
        refused = run("push", "--tls-verify=false", name, f"docker://{stack.domain}/bob/tiny:v1")
        assert refused.returncode != 0
        assert "denied" in refused.stderr.lower() or "unauthorized" in refused.stderr.lower()
    finally:
        run("rmi", "--force", name)
    resolved = image_resolver(stack.settings)(f"{stack.domain}/alice/tiny:v1")
    assert resolved.pinned.startswith(f"{stack.domain}/alice/tiny@sha256:")


def test_what_the_server_publishes_every_login_pulls_and_nobody_pushes(
    stack: Stack, tmp_path: Path
) -> None:
    """The service's namespace (the policy base's): published with a token only the server
    signs (`manieval admin publish-token`), pulled by any participant, pushed by none."""
    podman, skopeo = require_tool("podman"), require_tool("skopeo")
    run = podman_as_a_user(podman, tmp_path)
    local = f"localhost/manieval-published-test:{os.getpid()}"
    published = f"{stack.domain}/manieval/published-test:v1"

    _tiny_image(podman, local)
    try:
        token = registry.publish_token(stack.settings, repository="manieval/published-test")
        copied = subprocess.run(
            [
                *(skopeo, "copy", "--quiet", "--dest-tls-verify=false"),
                *("--dest-registry-token", token, f"containers-storage:{local}"),
                f"docker://{published}",
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert copied.returncode == 0, copied.stderr
        assert run("pull", "--tls-verify=false", published).returncode != 0  # anonymous: no
        login = run(
            "login", "--tls-verify=false", "-u", "bob", "-p", stack.tokens["bob"], stack.domain
        )
        assert login.returncode == 0, login.stderr
        pulled = run("pull", "--tls-verify=false", published)
        assert pulled.returncode == 0, pulled.stderr
        refused = run("push", "--tls-verify=false", local, f"docker://{published}")
        assert refused.returncode != 0
        assert "denied" in refused.stderr.lower() or "unauthorized" in refused.stderr.lower()
    finally:
        run("rmi", "--force", local, published)
