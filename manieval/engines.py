"""The embedded default's registry and container engine: what `manieval serve` and `manieval
demo` start, supervise and stop next to the server.

- The registry: Debian's ``docker-registry`` (CNCF distribution) with token authentication
  against this server (:mod:`server.registry`), its storage in ``<data_dir>/registry``, on
  ``MANIEVAL_EMBEDDED_REGISTRY_ADDR`` (``127.0.0.1:5000``).
- The engine: Podman's Docker API (``podman system service``) on a socket in
  ``<data_dir>/engine``; the worker's docker executor runs every policy image through it,
  pulling from the registry with the pull-only credential.

- The policy base: the image participants build on (docker/policy-base), copied from the
  engine into the registry as ``manieval/policy-base:bookworm`` (manieval/policy_base.py), so
  that the getting-started page's build pulls it from this service.

``MANIEVAL_DOCKER_ENGINE_URL`` names an engine of one's own instead (no Podman is started), and
``MANIEVAL_REGISTRY_DOMAIN`` a registry (none is started). What is
missing is said in one line, and image submissions are refused with that reason.
"""

from __future__ import annotations

import base64
import http.client
import json
import logging
import os
import shutil
import socket
from dataclasses import dataclass, field
from pathlib import Path

from pydantic_settings import BaseSettings, SettingsConfigDict

from manieval.client import is_loopback_domain
from manieval.supervise import Supervised
from server.kit.settings import Settings
from server.registry.config import TOKEN_PATH, registry_config
from server.registry.keys import ensure_signing_key
from server.registry.service import key_directory

log = logging.getLogger(__name__)

REGISTRY_BINARY = "docker-registry"
ENGINE_BINARY = "podman"
INSTALL = "apt-get install -y podman docker-registry"


class EngineSettings(BaseSettings):
    """What the embedded default starts next to the server (``MANIEVAL_*``; docs/server.md)."""

    model_config = SettingsConfigDict(env_prefix="MANIEVAL_", extra="ignore", frozen=True)

    embedded_registry: bool = True
    """Start the registry on the embedded default, unless ``MANIEVAL_REGISTRY_DOMAIN`` names
    one run elsewhere (docs/registry.md); false: none is started."""
    embedded_registry_addr: str = "127.0.0.1:5000"
    """Where the embedded registry listens (host:port); participants push there."""
    embedded_engine: bool = True
    """Start Podman's Docker API for the embedded worker; false: the worker uses
    ``MANIEVAL_DOCKER_ENGINE_URL`` (or runs no images). Never started with Celery workers:
    they have engines of their own."""
    docker_engine_url: str | None = None
    """An engine of one's own (``unix:///run/podman/podman.sock``): no Podman is started."""
    publish_policy_base: bool = True
    """Copy the engine's policy base into the embedded registry at start (when both are
    embedded), for participants to build on; false: nothing is copied (the pages name a base
    the registry already has, else say how to build it)."""


def engine_socket(data_dir: Path) -> Path:
    """Where the Podman that `manieval serve` (and the demo) starts for `data_dir` listens."""
    return data_dir / "engine" / "podman.sock"


def default_engine(data_dir: Path, system_url: str) -> tuple[str, list[str]]:
    """The engine a command run beside a local server uses when none is named: the Podman of
    the server's data directory while its socket exists, else `system_url`; and the places
    looked at, in order, for messages."""
    local = engine_socket(data_dir)
    looked = [f"unix://{local}", system_url]
    return (looked[0] if local.is_socket() else system_url), looked


@dataclass
class Engines:
    """The registry and the engine for one server at `server_url`; `start()`, then `stop()`."""

    settings: Settings
    server_url: str
    options: EngineSettings = field(default_factory=EngineSettings)
    missing: list[str] = field(default_factory=list)
    """What is not installed, by the name of its package."""
    registry: Supervised | None = None
    engine: Supervised | None = None
    engine_url: str | None = None
    """The Docker API the worker's docker executor uses (None: images cannot run)."""

    def __post_init__(self) -> None:
        self.home = self.settings.data_dir
        self.engine_url = self.options.docker_engine_url
        self.embeds_registry = (
            self.options.embedded_registry and self.settings.registry_domain is None
        )
        if self.embeds_registry:
            if shutil.which(REGISTRY_BINARY) is None:
                self.missing.append(REGISTRY_BINARY)
            else:
                self.registry = self._registry()
        wants_engine = self.options.embedded_engine and self.settings.queue == "inline"
        if self.engine_url is None and wants_engine:
            if shutil.which(ENGINE_BINARY) is None:
                self.missing.append(ENGINE_BINARY)
            else:
                self.engine = self._engine()

    # What the server and the worker are told ----------------------------------------------------

    @property
    def registry_domain(self) -> str | None:
        if self.embeds_registry:
            return self.options.embedded_registry_addr if self.registry is not None else None
        return self.settings.registry_domain

    def server_settings(self) -> Settings:
        """The server's settings with the embedded registry as its own (allowed, plain HTTP on
        the loopback address)."""
        domain = self.registry_domain
        if not self.embeds_registry or domain is None:
            return self.settings
        allowed = [*self.settings.allowed_registries]
        insecure = [*self.settings.insecure_registries]
        return self.settings.model_copy(
            update={
                "registry_domain": domain,
                "registry_internal_url": f"http://{domain}",
                "allowed_registries": [*allowed, domain] if domain not in allowed else allowed,
                "insecure_registries": [*insecure, domain] if domain not in insecure else insecure,
            }
        )

    def refusal(self) -> str | None:
        """Why image submissions cannot be taken now, in one sentence; None when they can."""
        if self.missing:
            return (
                f"image submissions are off on this server: {' and '.join(self.missing)} "
                f"{'is' if len(self.missing) == 1 else 'are'} not installed (the operator "
                f"runs: {INSTALL}, then restarts manieval serve)"
            )
        for child in (self.registry, self.engine):
            if child is not None and child.problem is not None:
                return f"image submissions are paused: {child.problem}"
        return None

    def missing_line(self) -> str | None:
        """The one line `manieval serve` prints when something is not installed."""
        if not self.missing:
            return None
        return (
            f"{' and '.join(self.missing)} not installed: policy images cannot be submitted "
            f"or run (bundled examples still can); install with: {INSTALL}"
        )

    # Starting and stopping ----------------------------------------------------------------------

    def start(self) -> list[str]:
        """Start what is installed and wait until it answers, then publish the policy base;
        the problems, one line each."""
        problems = []
        for child in (self.registry, self.engine):
            if child is not None and not child.start():
                problems.append(str(child.problem))
        if not problems:
            problem = self.publish_policy_base()
            if problem is not None:
                problems.append(problem)
        return problems

    def publish_policy_base(self) -> str | None:
        """Copy the engine's policy base into the embedded registry (manieval/policy_base.py);
        why it is not there, in one line, or None. Nothing to do without both embedded."""
        from manieval.policy_base import publish_policy_base

        domain = self.registry_domain
        if not self.options.publish_policy_base or not self.embeds_registry:
            return None
        if domain is None or self.engine is None or self.engine_url is None:
            return None
        return publish_policy_base(self.settings, domain=domain, engine_url=self.engine_url)

    def stop(self) -> None:
        for child in (self.engine, self.registry):
            if child is not None:
                child.stop()

    # The children ---------------------------------------------------------------------------------

    def _registry(self) -> Supervised:
        base = self.home / "registry"
        storage = base / "storage"
        storage.mkdir(parents=True, exist_ok=True)
        key = ensure_signing_key(key_directory(self.settings))
        addr = self.options.embedded_registry_addr
        config = registry_config(
            addr=addr,
            storage=storage,
            realm=f"{self.server_url}{TOKEN_PATH}",
            cert_path=key.cert_path,
            service=self.settings.registry_service,
            issuer=self.settings.registry_issuer,
        )
        path = base / "config.json"  # JSON is YAML
        path.write_text(json.dumps(config, indent=2))
        binary = shutil.which(REGISTRY_BINARY) or REGISTRY_BINARY
        return Supervised(
            "registry",
            [binary, "serve", str(path)],
            ready=lambda: _answers_http(addr),
            cwd=base,
            log_path=base / "registry.log",
            pid_path=base / "registry.pid",
        )

    def _engine(self) -> Supervised:
        path = engine_socket(self.home)
        base = path.parent
        base.mkdir(parents=True, exist_ok=True)
        self.engine_url = f"unix://{path}"
        env = {**os.environ, **self._engine_env(base)}
        binary = shutil.which(ENGINE_BINARY) or ENGINE_BINARY
        return Supervised(
            "podman",
            [binary, "system", "service", "--time=0", self.engine_url],
            ready=lambda: _answers_socket(path),
            env=env,
            cwd=base,  # Podman 4's conmon drops an "oom" file into its working directory
            log_path=base / "podman.log",
            pid_path=base / "podman.pid",
        )

    def _engine_env(self, base: Path) -> dict[str, str]:
        """The engine's own configuration: the registry over plain HTTP on loopback, pulled
        with the pull-only credential, and limits this kind of machine allows."""
        env: dict[str, str] = {}
        domain = self.registry_domain
        if domain is not None:
            password = self.settings.secret("registry_pull_password")
            auth = base64.b64encode(f"{self.settings.registry_pull_user}:{password}".encode())
            # The Docker API pulls without credentials use the engine's default auth file,
            # ``$XDG_RUNTIME_DIR/containers/auth.json``: a runtime directory of its own keeps
            # the pull credential apart from the logins of the machine's users.
            runtime = base / "run"
            (runtime / "containers").mkdir(parents=True, exist_ok=True, mode=0o700)
            auth_file = runtime / "containers" / "auth.json"
            fd = os.open(auth_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as out:
                json.dump({"auths": {domain: {"auth": auth.decode()}}}, out)
            runtime.chmod(0o700)
            env["XDG_RUNTIME_DIR"] = str(runtime)
            env["REGISTRY_AUTH_FILE"] = str(auth_file)
            if is_loopback_domain(domain):
                registries = base / "registries.conf"
                registries.write_text(f'[[registry]]\nlocation = "{domain}"\ninsecure = true\n')
                env["CONTAINERS_REGISTRIES_CONF"] = str(registries)
        if "CONTAINERS_CONF" not in os.environ:
            env["CONTAINERS_CONF"] = str(_containers_conf(base))
        return env


def _containers_conf(base: Path) -> Path:
    """Podman's defaults where they fail on hosts like ours (docker/containers.conf): runc
    when installed (crun refuses hybrid cgroups), ulimits the host allows."""
    lines = ["[containers]", 'default_ulimits = ["nofile=1024:1024", "nproc=8192:8192"]']
    if shutil.which("runc") is not None:
        lines += ["", "[engine]", 'runtime = "runc"']
    path = base / "containers.conf"
    path.write_text("\n".join(lines) + "\n")
    return path


def _answers_http(addr: str) -> bool:
    """The registry answers `/v2/` (401 with token auth on: it is up)."""
    host, port = addr.rsplit(":", 1)
    connection = http.client.HTTPConnection(host.strip("[]"), int(port), timeout=2.0)
    try:
        connection.request("GET", "/v2/")
        return connection.getresponse().status in (200, 401)
    finally:
        connection.close()


def _answers_socket(path: Path) -> bool:
    """Podman's Docker API answers `/_ping` on its unix socket."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.settimeout(2.0)
        conn.connect(str(path))
        conn.sendall(b"GET /_ping HTTP/1.0\r\nHost: engine\r\n\r\n")
        return conn.recv(64).startswith((b"HTTP/1.0 200", b"HTTP/1.1 200"))


def embedded_engines(settings: Settings, *, host: str, port: int) -> Engines:
    """The engines of `manieval serve` on `host:port`; prints the one line on what is missing.

    The registry sends clients to the server's token endpoint: on a wildcard address that is
    the loopback one (for other machines, name a registry of one's own with
    ``MANIEVAL_REGISTRY_DOMAIN``).
    """
    from rich.console import Console

    realm_host = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    engines = Engines(settings, server_url=f"http://{realm_host}:{port}")
    line = engines.missing_line()
    if line is not None:
        Console(stderr=True, soft_wrap=True).print(f"[yellow]{line}[/]")
    return engines
