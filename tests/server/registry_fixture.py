"""A real OCI registry for tests, and a client's way of pushing images to it.

``registry`` starts Debian's ``docker-registry`` (the CNCF distribution registry) once per test
session on a free 127.0.0.1 port. ``token_registry`` serves the same storage behind the Docker
token protocol, with a token service that signs JWTs by ``openssl``. ``push_image`` and
``push_index`` upload blobs and manifests over the distribution HTTP API, as a client would.

A test module imports the fixtures by their function names, which differ from the fixture names
so that test arguments do not shadow the import::

    from tests.server.registry_fixture import fixture_registry  # noqa: F401 - pytest fixture
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import random
import re
import shutil
import socket
import subprocess
import threading
import time
import urllib.parse
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest

REGISTRY_BINARY = "docker-registry"
OCI_INDEX = "application/vnd.oci.image.index.v1+json"
OCI_MANIFEST = "application/vnd.oci.image.manifest.v1+json"
OCI_CONFIG = "application/vnd.oci.image.config.v1+json"
OCI_LAYER = "application/vnd.oci.image.layer.v1.tar+gzip"
DOCKER_MANIFEST_LIST = "application/vnd.docker.distribution.manifest.list.v2+json"
DOCKER_MANIFEST = "application/vnd.docker.distribution.manifest.v2+json"
DOCKER_CONFIG = "application/vnd.docker.container.image.v1+json"
DOCKER_LAYER = "application/vnd.docker.image.rootfs.diff.tar.gzip"
_STARTUP_SECONDS = 15.0


@dataclass(frozen=True)
class LocalRegistry:
    domain: str
    url: str
    storage: Path
    token_requests: list[dict[str, str]] = field(default_factory=list)
    realm: str = ""  # the token service's URL, behind token auth


@dataclass(frozen=True)
class PushedImage:
    repository: str
    digest: str
    manifest: bytes
    media_type: str
    size_bytes: int


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def require_tool(name: str) -> str:
    """The tool's path; a failure in CI, a skip elsewhere, when it is not installed."""
    path = shutil.which(name)
    if path is None:
        message = f"{name} is not installed; run as root: apt-get install -y {name}"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture(scope="session", name="registry")
def fixture_registry(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalRegistry]:
    """An open registry with empty storage, for the whole session."""
    binary = require_tool(REGISTRY_BINARY)
    work = tmp_path_factory.mktemp("registry")
    storage = work / "storage"
    with serve_registry(binary, work, storage=storage) as domain:
        yield LocalRegistry(domain=domain, url=f"http://{domain}", storage=storage)


@pytest.fixture(scope="session", name="token_registry")
def fixture_token_registry(
    registry: LocalRegistry, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[LocalRegistry]:
    """``registry``'s storage behind token auth: anonymous pull tokens from a local service."""
    binary = require_tool(REGISTRY_BINARY)
    openssl = require_tool("openssl")
    work = tmp_path_factory.mktemp("token-registry")
    key, cert = work / "key.pem", work / "cert.pem"
    make_cert = "req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=manieval-test-tokens"
    subprocess.run(
        [openssl, *make_cert.split(), "-keyout", str(key), "-out", str(cert)],
        check=True,
        capture_output=True,
    )
    requests: list[dict[str, str]] = []
    tokens = _TokenService(openssl=openssl, key=key, cert=cert, requests=requests)
    with tokens.running() as realm:
        auth = {
            "token": {
                "realm": realm,
                "service": _TokenService.SERVICE,
                "issuer": _TokenService.ISSUER,
                "rootcertbundle": str(cert),
            }
        }
        with serve_registry(binary, work, storage=registry.storage, auth=auth) as domain:
            yield LocalRegistry(
                domain=domain,
                url=f"http://{domain}",
                storage=registry.storage,
                token_requests=requests,
                realm=realm,
            )


@contextmanager
def serve_registry(binary: str, work: Path, *, storage: Path, auth: Any = None) -> Iterator[str]:
    """Run ``docker-registry serve`` on a free port; yields its domain once ``/v2/`` answers."""

    def config(domain: str) -> dict[str, Any]:
        config: dict[str, Any] = {
            "version": "0.1",
            "log": {"level": "error", "accesslog": {"disabled": True}},
            "storage": {"filesystem": {"rootdirectory": str(storage)}, "delete": {"enabled": True}},
            "http": {"addr": domain, "secret": "manieval-tests"},
        }
        if auth is not None:
            config["auth"] = auth
        return config

    with serve_registry_config(binary, work, config) as domain:
        yield domain


@contextmanager
def serve_registry_config(
    binary: str, work: Path, config_for: Callable[[str], dict[str, Any]]
) -> Iterator[str]:
    """Run ``docker-registry serve`` with ``config_for(domain)`` on a free port; yields the
    domain once ``/v2/`` answers."""
    log = work / "registry.log"
    for _ in range(3):  # another process may take the free port before the registry does
        domain = f"127.0.0.1:{free_port()}"
        config = config_for(domain)
        (work / "config.yml").write_text(json.dumps(config, indent=2))  # JSON is YAML
        with log.open("ab") as out:
            process = subprocess.Popen(
                [binary, "serve", str(work / "config.yml")], stdout=out, stderr=subprocess.STDOUT
            )
        try:
            if _answers(process, f"http://{domain}/v2/"):
                yield domain
                return
        finally:
            process.terminate()
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    pytest.fail(f"docker-registry did not start:\n{log.read_text()[-3000:]}")


def _answers(process: subprocess.Popen[bytes], url: str) -> bool:
    deadline = time.monotonic() + _STARTUP_SECONDS
    while time.monotonic() < deadline and process.poll() is None:
        try:
            httpx.get(url, timeout=1.0)  # any answer will do: 401 behind token auth
            return True
        except httpx.TransportError:
            time.sleep(0.05)
    return False


class _TokenService:
    """Grants pull-only JWTs for any repository, as Docker Hub's auth service does for anyone."""

    SERVICE = "manieval-test-registry"
    ISSUER = "manieval-test-issuer"

    def __init__(
        self, *, openssl: str, key: Path, cert: Path, requests: list[dict[str, str]]
    ) -> None:
        self._openssl, self._key, self.requests = openssl, key, requests
        der = subprocess.run(
            [openssl, "x509", "-in", str(cert), "-outform", "DER"],
            check=True,
            capture_output=True,
        ).stdout
        self._x5c = base64.b64encode(der).decode()

    def token(self, scope: str) -> str:
        now = int(time.time())
        access = []
        kind, _, rest = scope.partition(":")
        name, _, actions = rest.rpartition(":")
        if kind == "repository" and "pull" in actions.split(","):
            access.append({"type": "repository", "name": name, "actions": ["pull"]})
        header = {"typ": "JWT", "alg": "RS256", "x5c": [self._x5c]}
        claims = {
            "iss": self.ISSUER,
            "sub": "",
            "aud": self.SERVICE,
            "exp": now + 300,
            "nbf": now - 10,
            "iat": now,
            "jti": os.urandom(8).hex(),
            "access": access,
        }
        signed = f"{_b64url(json.dumps(header).encode())}.{_b64url(json.dumps(claims).encode())}"
        signature = subprocess.run(
            [self._openssl, "dgst", "-sha256", "-sign", str(self._key)],
            input=signed.encode(),
            check=True,
            capture_output=True,
        ).stdout
        return f"{signed}.{_b64url(signature)}"

    @contextmanager
    def running(self) -> Iterator[str]:
        """Serve tokens on a free port; yields the realm URL."""
        service = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                query = dict(urllib.parse.parse_qsl(urllib.parse.urlsplit(self.path).query))
                service.requests.append(query)
                body = json.dumps({"token": service.token(query.get("scope", ""))}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: Any) -> None:
                pass

        server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield f"http://127.0.0.1:{server.server_address[1]}/token"
        finally:
            server.shutdown()
            server.server_close()
            thread.join(timeout=5)


class RegistryLogin(httpx.Auth):
    """What ``docker login`` sets up: on a registry's Bearer challenge, ask its token service
    (with these Basic credentials, if any) for the challenged scope, and retry with the token.
    Tokens are kept per scope; ``tokens`` lists every one received."""

    requires_response_body = True

    def __init__(self, username: str | None = None, password: str | None = None) -> None:
        self._basic = (
            httpx.BasicAuth(username, password) if username and password is not None else None
        )
        self._by_scope: dict[str, str] = {}
        self.tokens: list[str] = []
        self.refusals: list[httpx.Response] = []

    def auth_flow(self, request: httpx.Request) -> Generator[httpx.Request, httpx.Response, None]:
        response = yield request
        challenge = response.headers.get("WWW-Authenticate", "")
        if response.status_code != 401 or not challenge.lower().startswith("bearer "):
            return
        params = dict(re.findall(r'(\w+)="([^"]*)"', challenge))
        scope = params.get("scope", "")
        token = self._by_scope.get(scope)
        if token is None:
            query = {k: v for k, v in (("service", params.get("service")), ("scope", scope)) if v}
            ask = httpx.Request("GET", httpx.URL(params["realm"], params=query))
            if self._basic is not None:
                ask = next(self._basic.auth_flow(ask))
            answer = yield ask
            if answer.status_code != 200:
                self.refusals.append(answer)
                return
            token = answer.json()["token"]
            self._by_scope[scope] = token
            self.tokens.append(token)
        request.headers["Authorization"] = f"Bearer {token}"
        yield request


def _b64url(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def sha256_digest(data: bytes) -> str:
    return f"sha256:{hashlib.sha256(data).hexdigest()}"


def push_blob(http: httpx.Client, repository: str, data: bytes) -> str:
    """Upload one blob (POST then PUT, monolithic) and return its digest."""
    digest = sha256_digest(data)
    started = http.post(f"/v2/{repository}/blobs/uploads/")
    assert started.status_code == 202, started.text
    location = httpx.URL(started.headers["Location"]).copy_merge_params({"digest": digest})
    done = http.put(location, content=data, headers={"Content-Type": "application/octet-stream"})
    assert done.status_code == 201, done.text
    assert done.headers["Docker-Content-Digest"] == digest
    return digest


def push_manifest(
    http: httpx.Client, repository: str, reference: str, manifest: bytes, media_type: str
) -> str:
    """PUT a manifest by tag or digest; returns the digest of exactly these bytes."""
    response = http.put(
        f"/v2/{repository}/manifests/{reference}",
        content=manifest,
        headers={"Content-Type": media_type},
    )
    assert response.status_code == 201, response.text
    digest = sha256_digest(manifest)
    assert response.headers["Docker-Content-Digest"] == digest
    return digest


def push_image(
    http: httpx.Client,
    repository: str,
    reference: str,
    *,
    layer_sizes: Sequence[int],
    architecture: str = "amd64",
    media_type: str = OCI_MANIFEST,
    seed: int = 0,
) -> PushedImage:
    """Push a single-platform image with random layers; its size is config plus layers."""
    docker = media_type == DOCKER_MANIFEST
    rng = random.Random(f"{repository}:{reference}:{seed}")
    layers = [rng.randbytes(size) for size in layer_sizes]
    config = json.dumps(
        {
            "architecture": architecture,
            "os": "linux",
            "config": {"Cmd": ["python3", "-m", "policy"]},
            "rootfs": {"type": "layers", "diff_ids": [sha256_digest(x) for x in layers]},
        }
    ).encode()
    config_descriptor = {
        "mediaType": DOCKER_CONFIG if docker else OCI_CONFIG,
        "digest": push_blob(http, repository, config),
        "size": len(config),
    }
    layer_descriptors = [
        {
            "mediaType": DOCKER_LAYER if docker else OCI_LAYER,
            "digest": push_blob(http, repository, layer),
            "size": len(layer),
        }
        for layer in layers
    ]
    manifest = json.dumps(
        {
            "schemaVersion": 2,
            "mediaType": media_type,
            "config": config_descriptor,
            "layers": layer_descriptors,
        },
        indent=3,  # any bytes will do: the digest is of exactly what was pushed
    ).encode()
    digest = push_manifest(http, repository, reference, manifest, media_type)
    size = len(config) + sum(layer_sizes)
    return PushedImage(repository, digest, manifest, media_type, size)


def push_index(
    http: httpx.Client,
    repository: str,
    tag: str,
    images: Sequence[tuple[str, PushedImage]],
    *,
    media_type: str = OCI_INDEX,
) -> PushedImage:
    """Push an index over already pushed images, given as ("os/arch", image) pairs.

    Its ``size_bytes`` is 0: what an index weighs is the size of the image a platform pulls.
    """
    entries = []
    for platform, image in images:
        os_name, _, architecture = platform.partition("/")
        entries.append(
            {
                "mediaType": image.media_type,
                "digest": image.digest,
                "size": len(image.manifest),
                "platform": {"os": os_name, "architecture": architecture},
            }
        )
    index = json.dumps({"schemaVersion": 2, "mediaType": media_type, "manifests": entries}).encode()
    digest = push_manifest(http, repository, tag, index, media_type)
    return PushedImage(repository, digest, index, media_type, size_bytes=0)
