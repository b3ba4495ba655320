"""The participant's own container engine (Podman or Docker, through its command line) and
the service's registry: which engine, which registry, and logging the one in to the other with
the participant's API token (`manieval login`, `manieval push`)."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass

from rich.text import Text

from manieval import render
from manieval.client import ApiError, Client, is_loopback, is_loopback_domain
from manieval.errors import ExitCode, fail

ENGINES = ("podman", "docker")
REGISTRY_ENV = "MANIEVAL_REGISTRY"
EMBEDDED_REGISTRY = "127.0.0.1:5000"  # where `manieval serve` starts its registry by default
LOGIN_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Engine:
    """The participant's container engine, by its command."""

    name: str
    path: str

    def run(
        self, *args: str, stdin: str | None = None, timeout: float = LOGIN_TIMEOUT_S
    ) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [self.path, *args],
            input=stdin,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )


def find_engine(choice: str | None) -> Engine | None:
    """`choice`, else Podman, else Docker, when its command is installed."""
    for name in (choice,) if choice else ENGINES:
        path = shutil.which(name)
        if path is not None:
            return Engine(name, path)
    return None


def require_engine(choice: str | None) -> Engine:
    engine = find_engine(choice)
    if engine is None:
        wanted = choice or "podman or docker"
        fail(
            ExitCode.NO_ENGINE,
            f"no container engine here: {wanted} is not installed",
            "install one (Debian: apt-get install -y podman), build your image with it, "
            "and run this again",
        )
    return engine


def tls_flags(engine: Engine, domain: str) -> list[str]:
    """Podman speaks plain HTTP to a loopback registry only when told (Docker does anyway)."""
    return ["--tls-verify=false"] if engine.name == "podman" and is_loopback_domain(domain) else []


def registry_of(client: Client, option: str | None) -> str:
    """--registry (or MANIEVAL_REGISTRY), else the registry the server names, else on a local
    server that does not say, the embedded default's; exits when the server runs none."""
    domain = find_registry(client, option)
    if domain is None and is_loopback(client.server):
        domain = EMBEDDED_REGISTRY
    if not domain:
        fail(
            ExitCode.NOT_FOUND,
            f"{client.server} names no registry of its own",
            "push your image to a registry the challenge allows and use: manieval submit "
            f"(or name the service's registry: --registry HOST:PORT, {REGISTRY_ENV})",
        )
    return domain


def find_registry(client: Client, option: str | None) -> str | None:
    """--registry, else the domain of the server's own registry; "" when the server says it
    runs none, None when it does not say (a server without ``GET /api/v1/registry``)."""
    if option:
        return option.strip().removeprefix("https://").removeprefix("http://").rstrip("/")
    try:
        found = client.call("GET", "/registry")
    except ApiError as exc:
        if exc.status != 404:
            raise
        return "" if "registry" in exc.message else None
    domain = found.get("domain") if isinstance(found, dict) else None
    return domain if isinstance(domain, str) and domain else None


# Logging the engine in --------------------------------------------------------------------------


def login_command(engine_name: str, domain: str, username: str) -> str:
    """The one command a participant runs to log an engine in themselves."""
    flags = " --tls-verify=false" if engine_name == "podman" and is_loopback_domain(domain) else ""
    return f"{engine_name} login{flags} --username {username} {domain}   (password: an API token)"


def engine_login(engine: Engine, *, domain: str, username: str, token: str) -> str | None:
    """Log `engine` in to the registry with the API token; None when done, else why not."""
    args = ["login", *tls_flags(engine, domain), "--username", username, "--password-stdin", domain]
    try:
        done = engine.run(*args, stdin=token + "\n")
    except (OSError, subprocess.TimeoutExpired) as exc:
        return str(exc)
    if done.returncode != 0:
        return last_line(done.stderr or done.stdout) or f"exit status {done.returncode}"
    return None


def login_engine_after(client: Client, *, username: str) -> None:
    """After `manieval login`: log the local engine in to the service's registry too, or say
    the one command that does."""
    err = render.stderr()
    try:
        domain = find_registry(client, os.environ.get(REGISTRY_ENV))
    except ApiError:
        return
    if not domain:  # none, or not said: nothing to log in to
        return
    engine = find_engine(None)
    if engine is None:
        err.print(
            f"to push images later, install Podman or Docker and log it in to {domain}: "
            f"{login_command('podman', domain, username)}",
            highlight=False,
        )
        return
    assert client.token is not None
    problem = engine_login(engine, domain=domain, username=username, token=client.token)
    if problem is None:
        err.print(f"{engine.name} logged in to the registry {domain} as {username}")
        return
    err.print(
        Text(f"{engine.name} could not log in to {domain} ({problem}); ", style="yellow")
        + Text(f"later: {login_command(engine.name, domain, username)}")
    )


def last_line(text: str) -> str:
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[-1][-400:] if lines else ""


def logged_in_as(engine: Engine, domain: str) -> str | None:
    """The user the engine is logged in to `domain` as (Podman says; Docker: unknown)."""
    if engine.name != "podman":
        return None
    done = engine.run("login", "--get-login", *tls_flags(engine, domain), domain)
    return done.stdout.strip() or None if done.returncode == 0 else None


def ensure_login(engine: Engine, *, domain: str, username: str, token: str | None) -> None:
    """Log the engine in with the API token unless it already is, as this user."""
    if token is None or logged_in_as(engine, domain) == username:
        return
    problem = engine_login(engine, domain=domain, username=username, token=token)
    if problem is None:
        return
    lowered = problem.lower()
    if any(s in lowered for s in ("connection refused", "no such host", "i/o timeout")):
        fail(
            ExitCode.REGISTRY_UNREACHABLE,
            f"the registry {domain} does not answer ({problem})",
            "is the service running? its operator sees why in the server's log",
        )
    fail(
        ExitCode.PUSH_REFUSED,
        f"the registry {domain} refused the login of {username}: {problem}",
        f"log in yourself: {login_command(engine.name, domain, username)}",
    )
