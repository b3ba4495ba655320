"""The getting-started page of a challenge: from nothing to a ranked submission, every command
filled in for this service (its address, its registry, the downloads it serves) and the
observation and action contract generated from the challenge's suite. Its commands are what
tests/web/test_getting_started_e2e.py runs, in a fresh virtualenv."""

from __future__ import annotations

from dataclasses import dataclass

from fastapi import APIRouter, Request
from fastapi.responses import Response

from server.accounts.deps import ViewerDep
from server.challenges.contract import contract_of
from server.challenges.service import get_challenge, suite_of
from server.downloads.artifacts import (
    TEMPLATE_DIR,
    served,
    source_dir,
    source_file,
    wheel_files,
)
from server.kit.deps import DBDep
from server.kit.pages import render
from server.models import Challenge
from server.registry.published import LOCAL_POLICY_BASE
from server.submissions.deps import services
from server.submissions.submit_pages import published_base, server_flag, template_commands

router = APIRouter(include_in_schema=False)

PLACEHOLDER_NAME = "NAME"  # the user name, where the reader is not signed in
PLACEHOLDER_EMAIL = "you@example.org"
VENV = "manieval-env"


@dataclass(frozen=True)
class StartCommands:
    """The page's commands, step by step: each list is one block to paste into a shell."""

    install: list[str]
    account: list[str]
    template: list[str]
    simulator: list[str]  # none where the service does not serve its source
    evaluate: list[str]
    build: list[str]
    push: list[str]
    board: list[str]


def start_commands(
    request: Request,
    *,
    challenge: Challenge,
    username: str | None,
    phase: str,
    published: str | None,
) -> StartCommands:
    """Every command of the page, for this service and reader."""
    base = str(request.base_url).rstrip("/")
    server = server_flag(request)
    name = username or PLACEHOLDER_NAME
    wheels = " ".join(f"{base}/downloads/{name}" for name in wheel_files())
    account = (
        [] if username else [f"manieval register -u {name} --email {PLACEHOLDER_EMAIL}{server}"]
    )
    slug = challenge.slug
    fetch, build = template_commands(request, published=published)
    return StartCommands(
        install=[f"python3 -m venv {VENV}", f". {VENV}/bin/activate", f"pip install {wheels}"],
        account=[*account, f"manieval login -u {name}{server}"],
        template=fetch,
        simulator=[
            f"curl -fsSLO {base}/downloads/{source_file()}",
            f"tar xzf {source_file()}",
            f"make -C {source_dir()} install-evaluator",
            f". {source_dir()}/.venv/bin/activate",
        ]
        if source_file() in served()
        else [],
        evaluate=[
            f"curl -fsSL {base}/challenges/{slug}/suite.yaml -o {slug}.yaml",
            f"manieval evaluate --policy {TEMPLATE_DIR} --suite {slug}.yaml --phase {phase}"
            " --episodes 1",
        ],
        build=build,
        push=[f"manieval push my-policy:v1 --challenge {slug} --wait"],
        board=[f"manieval leaderboard {slug}"],
    )


@router.get("/challenges/{slug}/start")
def getting_started(slug: str, request: Request, who: ViewerDep, db: DBDep) -> Response:
    """Install, the contract, the template, a local run, build, push, the board."""
    challenge = get_challenge(db, slug=slug)
    suite = suite_of(challenge)
    contract = contract_of(suite)
    phase = contract.public_phases[0] if contract.public_phases else next(iter(suite.phases))
    username = who.user.username if who.user is not None else None
    published = published_base(request)
    return render(
        request,
        who,
        "start.html",
        challenge=challenge,
        contract=contract,
        commands=start_commands(
            request, challenge=challenge, username=username, phase=phase, published=published
        ),
        registry=services(request).settings.registry_domain,
        published_base=published,
        local_base=LOCAL_POLICY_BASE,
    )


@router.get("/challenges/{slug}/suite.yaml")
def suite_file(slug: str, db: DBDep) -> Response:
    """The suite as the challenge stores it: what `manieval evaluate --suite FILE` runs."""
    challenge = get_challenge(db, slug=slug)
    return Response(challenge.suite_yaml, media_type="application/yaml")
