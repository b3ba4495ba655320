"""`manieval demo`: the whole service on one machine, with filled leaderboards.

It starts the embedded server (SQLite, in-process worker), loads the two tracks' challenges (the
core suite on state observations, the visual suite on cameras; the visual challenge a track of
the core one, so the core challenge's page shows both boards) with short episode counts,
creates the `demo` account, and submits the bundled example policies through the public API,
exactly like any participant; then it follows them live and keeps serving until interrupted. A
second run reuses the same data and skips finished work.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.text import Text
from sqlalchemy import select

from evaluator.suite import load_suite
from manieval import render
from manieval.client import DEFAULT_SERVER, Client
from manieval.engines import embedded_engines
from manieval.errors import handled
from manieval.follow import follow_all
from manieval.quiet import service_logging
from manieval.service import Service
from server.accounts import service as accounts
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from server.models import User


@dataclass(frozen=True)
class Track:
    """A challenge the demo loads, narrowed as a try-out, and the bundled policies it submits
    there as baselines."""

    challenge: str
    policies: tuple[str, ...]
    name: str = ""
    """Its name among the demo's tracks (docs/server.md, Tracks)."""
    track_of: str | None = None
    """The challenge heading the demo's tracks (None: this one heads them)."""
    tasks: tuple[str, ...] | None = None
    conditions: tuple[str, ...] | None = None
    episodes: int | None = None
    """Episodes per task (None: the demo's `--episodes`)."""
    note: str = ""
    """Said on the challenge's page, after the suite's description."""


CORE = Track(challenge="maniskill-core", policies=("scripted", "random"), name="state")
# Camera frames cost tens of milliseconds each on a CPU: the visual track runs small, so that
# the demo's first leaderboards still come within 90 s on 2 cores (docs/capacity.md).
VISUAL = Track(
    challenge="maniskill-visual",
    policies=("scripted",),
    name="visual",
    track_of=CORE.challenge,
    tasks=("PickCube-v1", "PushCube-v1"),
    conditions=("nominal",),
    episodes=1,
    note=(
        "**In this demo** the visual track runs small, so that the first leaderboards come "
        "within 90 s on 2 cores: PickCube-v1 and PushCube-v1 only, 1 episode each, under the "
        "nominal condition only. The whole suite: `manieval evaluate --policy "
        "examples/policies/scripted --suite maniskill-visual`."
    ),
)
TRACKS = (CORE, VISUAL)
CHALLENGE = CORE.challenge  # where a participant's own first policy goes
ENDED_BADLY = {"failed", "error", "cancelled", "timed_out"}
LOG_FILE = "demo.log"
LOG_TAIL_LINES = 5

console = Console(stderr=True, soft_wrap=True)
JSON = dict[str, Any]


def run_demo(
    settings: Settings,
    *,
    host: str,
    port: int,
    episodes: int,
    exit_when_done: bool,
    with_engines: bool = True,
) -> int:
    """Serve with the examples evaluated; with `exit_when_done`, 0 only if both succeeded."""
    url = f"http://{host}:{port}"
    log_path = settings.data_dir / LOG_FILE
    service_logging(log_path)
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        for track in TRACKS:
            load_challenge(
                db,
                track.challenge,
                challenge_options(track, episodes),
                seed_secret=settings.secret("seed_secret"),
            )
        password = _demo_account(db, settings.data_dir)
    engines = embedded_engines(settings, host=host, port=port) if with_engines else None
    service = Service(settings, host=host, port=port, sessions=sessions, engines=engines)
    for problem in service.start_engines():
        console.print(f"[yellow]{problem}[/]")
    if not service.start():
        console.print(f"[red]the server could not start on {url} (port in use?)[/]")
        return 1
    try:  # from here a Ctrl-C stops the service, and its runs are recorded as interrupted
        console.print(f"ManiEval is running at [bold]{url}[/] (API docs: {url}/docs)")
        console.print(f"data: {settings.data_dir} (log: {log_path})")
        console.print(f"log in as [bold]demo[/] / {password}")
        if engines is not None and engines.registry_domain is not None:
            _print_participant_path(url, engines.registry_domain)
        with handled(), Client(url) as anonymous:
            token = anonymous.create_token(login="demo", password=password, name="demo")["token"]
        with handled(), Client(url, token=token) as client:
            names = _submit_missing(client)
            finals = follow_all(client, list(names), names=names, console=console)
            all_succeeded = _report(client, finals, url=url, log_path=log_path)
        if exit_when_done:
            return 0 if all_succeeded else 1
        console.print("serving; press Ctrl-C to stop")
        service.wait()
    except KeyboardInterrupt:
        pass
    finally:
        service.stop()
    if service.interrupted:
        runs = ", ".join(map(str, service.interrupted))
        console.print(f"stopped: submissions {runs} were interrupted; they run again next time")
    return 0


def challenge_options(track: Track, episodes: int) -> ChallengeOptions:
    """How the demo loads a track's challenge."""
    description = None
    if track.note:
        description = f"{load_suite(track.challenge).description}\n\n{track.note}"
    return ChallengeOptions(
        description=description,
        quota_per_day=50,
        quota_concurrent=len(track.policies),
        episodes=track.episodes or episodes,
        tasks=track.tasks,
        conditions=track.conditions,
        track=track.name or None,
        track_of=track.track_of,
    )


def participant_commands(url: str, registry: str, *, user: str = "NAME") -> list[str]:
    """A participant's path from nothing to a ranked policy image, as shell commands."""
    server = "" if url == DEFAULT_SERVER else f" --server {url}"
    return [
        f"manieval register -u {user} --email {user}@example.org{server}",
        f"manieval login -u {user}{server}   # also logs Podman/Docker in to {registry}",
        "docker/policy-base/build.sh   # the base image, once, if `make install` did not (as root)",
        "cp -r examples/policy-template my-policy && cp -r evaluator/sdk/manieval_sdk my-policy/",
        "podman build -t my-policy my-policy   # or: docker build",
        f"manieval push my-policy --challenge {CHALLENGE} --wait{server}",
    ]


def _print_participant_path(url: str, registry: str) -> None:
    console.print(f"registry: [bold]{registry}[/] (participants push their policy images here)")
    console.print("a participant's own policy, from the repository's directory:")
    for command in participant_commands(url, registry):
        console.print(f"  {command}", markup=False, highlight=False)


def _demo_account(db: object, data_dir: Path) -> str:
    from sqlalchemy.orm import Session

    assert isinstance(db, Session)
    path = data_dir / "demo-password"
    if path.exists() and db.scalar(select(User).where(User.username == "demo")) is not None:
        return path.read_text().strip()
    password = secrets.token_urlsafe(12)
    existing = db.scalar(select(User).where(User.username == "demo"))
    if existing is None:
        accounts.register(
            db, username="demo", email="demo@example.org", password=password, admin=True
        )
    else:
        accounts.set_password(db, existing, password)
    path.write_text(password + "\n")
    path.chmod(0o600)
    return password


def _submit_missing(client: Client) -> dict[int, str]:
    """Submit each track's example policies that have no queued, running or succeeded
    submission there yet; the submissions to follow, with their images and challenges."""
    names: dict[int, str] = {}
    for track in TRACKS:
        mine = client.my_submissions(challenge=track.challenge, per_page=200)
        for name in track.policies:
            image = f"local:{name}"
            label = f"{image} on {track.challenge}"
            current = [s for s in mine if s["image"] == image and s["state"] not in ENDED_BADLY]
            if current:
                names[current[0]["id"]] = label
                continue
            s = client.submit(
                challenge=track.challenge,
                phase="dev",
                image=image,
                description=f"bundled example policy: {name}",
                public=True,
            )
            client.call("PATCH", f"/submissions/{s['id']}", json={"baseline": True})
            console.print(f"submitted {label} as submission {s['id']}")
            names[s["id"]] = label
    return names


def _report(client: Client, finals: list[JSON], *, url: str, log_path: Path) -> bool:
    """The board if anything succeeded; what failed, and what to do next. True: all done."""
    failed = [s for s in finals if s["state"] != "succeeded"]
    scored = {s["challenge"] for s in finals if s["state"] == "succeeded"}
    for challenge in (t.challenge for t in TRACKS if t.challenge in scored):
        board = client.leaderboard(challenge, phase="dev", page=1, per_page=50).json()
        render.stdout().print(render.leaderboard_table(board))
        console.print(f"leaderboard: [bold]{url}/challenges/{challenge}/leaderboard[/]")
        console.print(f"  (JSON: {url}/api/v1/challenges/{challenge}/leaderboard)")
    if not failed:
        return True
    some = "none" if len(failed) == len(finals) else f"{len(failed)} of {len(finals)}"
    console.print(Text(f"{some} of the example policies succeeded:", style="bold red"))
    for s in failed:
        where = f"{s['image']} on {s['challenge']}"
        console.print(Text(f"  submission {s['id']} ({where}) {s['state']}: {s['reason']}"))
        tail = client.logs(s["id"])["log_tail"].strip().splitlines()[-LOG_TAIL_LINES:]
        if tail:
            console.print(Text("    its policy's log ends with:", style="dim"))
            for line in tail:
                console.print(Text(f"      {render.printable(line, terminal=True)}"))
        console.print(Text(f"    {url}/submissions/{s['id']}"))
    for line in next_steps([s["state"] for s in failed], log_path=log_path):
        console.print(Text(line), highlight=False)
    return False


def next_steps(states: list[str], *, log_path: Path) -> list[str]:
    """What to do after the examples ended in these states (not `succeeded`)."""
    steps = ["next:"]
    if "error" in states:
        steps.append(f"  the service could not run them (not the policies' fault): see {log_path}")
    if "failed" in states or "timed_out" in states:
        steps.append(
            "  the policies broke (their reasons and logs are above); run one alone, without "
            "the service, to see the policy's and the simulator's own errors:"
        )
        steps.append(
            "    manieval evaluate --policy examples/policies/random --tasks PickCube-v1 "
            "--condition nominal --episodes 1"
        )
    if "cancelled" in states:
        steps.append("  they were cancelled (on the web or with manieval cancel)")
    steps.append(
        "  then run manieval demo again: what succeeded is kept, the rest is submitted again"
    )
    return steps
