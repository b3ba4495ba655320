"""`manieval push`: a local policy image into the service's registry, under the participant's
own namespace, submitted pinned by its digest.

The engine is the participant's own Podman or Docker, driven through its command line so that
its configuration (storage, credentials, proxies) is the one they use every day; its progress
lines are shown while the layers upload.
"""

from __future__ import annotations

import re
import subprocess
import tempfile
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, NoReturn

import typer
from rich.text import Text

from manieval import render
from manieval.client import MethodInfo
from manieval.connect import JsonOption, ServerOption, connect, print_json
from manieval.engine_login import (
    ENGINES,
    REGISTRY_ENV,
    Engine,
    ensure_login,
    last_line,
    registry_of,
    require_engine,
    tls_flags,
)
from manieval.errors import ExitCode, fail, handled, server_flag
from manieval.participant import CodeOption, MethodOption, PaperOption, wait_and_report

PUSH_TIMEOUT_S = 3600.0
_COMPONENT = re.compile(r"[a-z0-9]+(?:(?:[._]|__|-+)[a-z0-9]+)*")
_TAG = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")
_DIGEST = re.compile(r"sha256:[0-9a-f]{64}")


# Pushing ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    domain: str
    repository: str  # <namespace>/<name>
    tag: str

    @property
    def tagged(self) -> str:
        return f"{self.domain}/{self.repository}:{self.tag}"

    def pinned(self, digest: str) -> str:
        return f"{self.domain}/{self.repository}@{digest}"


def target_for(
    image: str, *, domain: str, namespace: str, name: str | None, tag: str | None
) -> Target:
    """Where `image` goes: `<domain>/<namespace>/<name>:<tag>`, the name and tag taken from the
    local reference unless given."""
    local_name, local_tag = split_reference(image)
    name = name or local_name.rsplit("/", 1)[-1]
    name = name.lower()
    if not all(_COMPONENT.fullmatch(part) for part in name.split("/")):
        raise ValueError(
            f"{name!r} is not a repository name: lower-case letters, digits, and . _ - inside"
        )
    tag = tag or local_tag or "latest"
    if not _TAG.fullmatch(tag):
        raise ValueError(f"{tag!r} is not a tag: letters, digits, _ . - (at most 128)")
    return Target(domain=domain, repository=f"{namespace}/{name}", tag=tag)


def split_reference(image: str) -> tuple[str, str | None]:
    """(name, tag) of a local reference; no tag when it has none or names a digest."""
    name = image.split("@", 1)[0]
    last = name.rsplit("/", 1)[-1]
    if ":" in last:
        name, tag = name.rsplit(":", 1)
        return name, tag
    return name, None


def image_exists(engine: Engine, image: str) -> bool:
    done = engine.run("image", "inspect", "--format", "{{.Id}}", image)
    return done.returncode == 0


def push_image(engine: Engine, image: str, target: Target) -> str:
    """Tag and push; the digest the registry stored. Progress lines go to stderr as they come."""
    tagged = engine.run("tag", image, target.tagged)
    if tagged.returncode != 0:
        fail(ExitCode.IMAGE_NOT_FOUND, f"cannot tag {image}: {last_line(tagged.stderr)}")
    with tempfile.TemporaryDirectory(prefix="manieval-push-") as work:
        digest_file = Path(work) / "digest"
        args = ["push", *tls_flags(engine, target.domain)]
        if engine.name == "podman":
            args += ["--digestfile", str(digest_file)]
        output = _stream([engine.path, *args, target.tagged])
        if output.code != 0:
            _push_refused(engine, target, output.lines)
        digest = digest_file.read_text().strip() if digest_file.exists() else ""
    if not _DIGEST.fullmatch(digest):
        # docker push ends with "<tag>: digest: sha256:... size: N"
        found = _DIGEST.findall("\n".join(output.lines))
        digest = found[-1] if found else ""
    if not digest:
        fail(ExitCode.SERVER_ERROR, f"{engine.name} pushed {target.tagged} but named no digest")
    return digest


@dataclass(frozen=True)
class _Output:
    code: int
    lines: list[str]


def _stream(argv: list[str]) -> _Output:
    """Run, echoing its output to stderr line by line, and keep the last lines."""
    kept: deque[str] = deque(maxlen=60)
    err = render.stderr()
    process = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace"
    )
    assert process.stdout is not None
    try:
        for line in process.stdout:
            line = line.rstrip()
            if line:
                kept.append(line)
                err.print(Text(f"  {line}", style="dim"), highlight=False)
        code = process.wait(timeout=PUSH_TIMEOUT_S)
    except BaseException:
        process.kill()
        process.wait()
        raise
    return _Output(code, list(kept))


def _push_refused(engine: Engine, target: Target, lines: list[str]) -> NoReturn:
    """The engine's failure, said as what it means for the participant."""
    text = "\n".join(lines).lower()
    last = last_line("\n".join(lines))
    if any(
        s in text
        for s in ("connection refused", "no such host", "i/o timeout", "network is unreachable")
    ):
        fail(
            ExitCode.REGISTRY_UNREACHABLE,
            f"the registry {target.domain} does not answer",
            f"({last})",
            "is the service running? its operator sees why in the server's log",
        )
    if "denied" in text:
        fail(
            ExitCode.PUSH_REFUSED,
            f"the registry refused the push to {target.tagged}: {last}",
            f"you may push only under {target.domain}/{target.repository.split('/')[0]}/",
        )
    if _says(text, r"\b401\b", "unauthorized", "authentication required"):
        fail(
            ExitCode.PUSH_REFUSED,
            f"the registry refused the push: {engine.name}'s login to {target.domain} is not "
            "valid (an API token revoked or expired)",
            f"({last})",
            "run manieval login again: it logs the engine in with a new token",
        )
    if _says(text, r"\b413\b", "too large", "size limit"):
        fail(
            ExitCode.PUSH_REFUSED,
            f"the registry refused the image as too large: {last}",
            "make it smaller (fewer layers, no build caches or datasets in it)",
        )
    if _says(text, r"\b429\b", "quota", "toomanyrequests", "too many requests"):
        fail(ExitCode.PUSH_REFUSED, f"the registry refused the push (quota): {last}")
    fail(ExitCode.PUSH_REFUSED, f"{engine.name} push failed: {last}")


def _says(text: str, status: str, *phrases: str) -> bool:
    """Whether the engine's output names this HTTP `status` (a word, not digits inside a
    digest) or one of the phrases."""
    return re.search(status, text) is not None or any(p in text for p in phrases)


# The command ------------------------------------------------------------------------------------


def push(
    image: Annotated[str, typer.Argument(help="A local image: my-policy, localhost/p:v2.")],
    challenge: Annotated[str, typer.Option("--challenge", "-c", help="The challenge's name.")],
    phase: Annotated[str, typer.Option(help="The phase.")] = "dev",
    name: Annotated[
        str | None,
        typer.Option(help="Repository name under your namespace (default: the image's name)."),
    ] = None,
    tag: Annotated[
        str | None, typer.Option(help="Tag in the registry (default: the image's, or latest).")
    ] = None,
    description: Annotated[str, typer.Option(help="A note shown with the submission.")] = "",
    method: MethodOption = None,
    paper_url: PaperOption = None,
    code_url: CodeOption = None,
    private: Annotated[
        bool, typer.Option("--private", help="Keep it off the public leaderboard.")
    ] = False,
    wait: Annotated[
        bool, typer.Option("--wait", help="Follow it to its end; exit 0 only if it succeeds.")
    ] = False,
    engine: Annotated[
        str | None,
        typer.Option(help="podman or docker (default: the one installed, Podman first)."),
    ] = None,
    registry: Annotated[
        str | None,
        typer.Option(
            envvar=REGISTRY_ENV,
            show_default=False,
            help="The service's registry (default: as the server says).",
        ),
    ] = None,
    as_json: JsonOption = False,
    server: ServerOption = None,
) -> None:
    """Push a local image to the service's registry under your name; submit it by digest."""
    if engine is not None and engine not in ENGINES:
        raise typer.BadParameter("podman or docker", param_hint="--engine")
    info = MethodInfo(method, paper_url, code_url)
    if (problem := info.link_problem()) is not None:  # before the upload, not after it
        raise typer.BadParameter(problem[1], param_hint=problem[0])
    chosen = require_engine(engine)
    err = render.stderr()
    with handled(), connect(server, login="required") as client:
        username = client.me()["user"]["username"]
        domain = registry_of(client, registry)
        client.challenge(challenge)  # an unknown challenge fails before the upload
        if not image_exists(chosen, image):
            fail(
                ExitCode.IMAGE_NOT_FOUND,
                f"{chosen.name} has no image {image}",
                f"build it first: {chosen.name} build -t {image} DIRECTORY "
                f"(see yours: {chosen.name} images)",
            )
        try:
            target = target_for(image, domain=domain, namespace=username, name=name, tag=tag)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--name/--tag") from None
        ensure_login(chosen, domain=domain, username=username, token=client.token)
        err.print(f"pushing {image} to {target.tagged} with {chosen.name}")
        started = time.monotonic()
        digest = push_image(chosen, image, target)
        err.print(
            f"pushed {target.tagged} in {time.monotonic() - started:.1f} s: {digest}",
            highlight=False,
        )
        s = client.submit(
            challenge=challenge,
            phase=phase,
            image=target.pinned(digest),
            description=description,
            public=not private,
            method=info,
        )
        err.print(f"submission {s['id']} accepted: {s['pinned_image']}", highlight=False)
        if not wait:
            if as_json:
                print_json(s)
            err.print(f"follow it: manieval status {s['id']} --wait{server_flag(client.server)}")
            return
        wait_and_report(client, s["id"], as_json=as_json)
