"""`manieval demo`: the whole service on one machine, with a filled leaderboard.

It starts the embedded server (SQLite, in-process worker), loads the core challenge with a
short episode count, creates the `demo` account, and submits the bundled example policies
through the public API, exactly like any participant; then it follows them live and keeps
serving until interrupted. A second run reuses the same data and skips finished work.
"""

from __future__ import annotations

import secrets
import time
from pathlib import Path

import httpx
from rich.console import Console
from rich.table import Table
from sqlalchemy import select

from manieval.client import DEFAULT_SERVER
from manieval.engines import embedded_engines
from manieval.service import Service
from server.accounts import service as accounts
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from server.models import User

CHALLENGE = "maniskill-core"
POLICIES = ("scripted", "random")
FINAL = {"succeeded", "failed", "error", "cancelled", "timed_out"}

console = Console(stderr=True, soft_wrap=True)


def run_demo(
    settings: Settings,
    *,
    host: str,
    port: int,
    episodes: int,
    exit_when_done: bool,
    with_engines: bool = True,
) -> int:
    url = f"http://{host}:{port}"
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions.begin() as db:
        load_challenge(
            db,
            CHALLENGE,
            ChallengeOptions(quota_per_day=50, quota_concurrent=len(POLICIES), episodes=episodes),
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
    console.print(f"ManiEval is running at [bold]{url}[/] (API docs: {url}/docs)")
    console.print(f"data: {settings.data_dir}; log in as [bold]demo[/] / {password}")
    if engines is not None and engines.registry_domain is not None:
        _print_participant_path(url, engines.registry_domain)
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            token = client.post(
                "/api/v1/auth/token", json={"login": "demo", "password": password, "name": "demo"}
            ).json()["token"]
            client.headers["Authorization"] = f"Bearer {token}"
            ids = _submit_missing(client)
            _follow(client, ids)
            _print_leaderboard(client)
        console.print(f"leaderboard: [bold]{url}/challenges/{CHALLENGE}/leaderboard[/]")
        console.print(f"  (JSON: {url}/api/v1/challenges/{CHALLENGE}/leaderboard)")
        if exit_when_done:
            return 0
        console.print("serving; press Ctrl-C to stop")
        service.wait()
    except KeyboardInterrupt:
        pass
    finally:
        service.stop()
    return 0


def participant_commands(url: str, registry: str, *, user: str = "NAME") -> list[str]:
    """A participant's path from nothing to a ranked policy image, as shell commands."""
    server = "" if url == DEFAULT_SERVER else f" --server {url}"
    return [
        f"manieval register -u {user} --email {user}@example.org{server}",
        f"manieval login -u {user}{server}   # also logs Podman/Docker in to {registry}",
        "docker/policy-base/build.sh   # the base image, once (as root, about a minute)",
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


def _submit_missing(client: httpx.Client) -> list[int]:
    """Submit each example policy that has no queued, running or succeeded submission yet."""
    mine = client.get(
        "/api/v1/submissions", params={"challenge": CHALLENGE, "per_page": 200}
    ).json()["items"]
    ids: list[int] = []
    for name in POLICIES:
        image = f"local:{name}"
        current = [
            s
            for s in mine
            if s["image"] == image
            and s["state"] not in {"failed", "error", "cancelled", "timed_out"}
        ]
        if current:
            ids.append(current[0]["id"])
            continue
        r = client.post(
            "/api/v1/submissions",
            json={
                "challenge": CHALLENGE,
                "phase": "dev",
                "image": image,
                "description": f"bundled example policy: {name}",
            },
        )
        r.raise_for_status()
        sid = r.json()["id"]
        client.patch(f"/api/v1/submissions/{sid}", json={"baseline": True}).raise_for_status()
        console.print(f"submitted {image} as submission {sid}")
        ids.append(sid)
    return ids


def _follow(client: httpx.Client, ids: list[int]) -> None:
    last: dict[int, str] = {}
    while True:
        pending = 0
        for sid in ids:
            s = client.get(f"/api/v1/submissions/{sid}").json()
            progress = s.get("progress") or {}
            line = f"submission {sid} ({s['image']}): {s['state']}"
            if s["state"] == "running" and progress:
                line += f" {progress.get('done')}/{progress.get('total')} episodes"
                line += f" ({progress.get('task')}, {progress.get('condition')})"
            if s["state"] in FINAL:
                line += f": {s['reason']}"
            else:
                pending += 1
            if last.get(sid) != line:
                console.print(line)
                last[sid] = line
        if not pending:
            return
        time.sleep(1.0)


def _print_leaderboard(client: httpx.Client) -> None:
    board = client.get(f"/api/v1/challenges/{CHALLENGE}/leaderboard").json()
    tasks = sorted({t for row in board["items"] for t in row["tasks"]})
    table = Table(title=f"{CHALLENGE} leaderboard (dev)")
    for column in ["rank", "user", "submission", "score", *tasks]:
        table.add_column(column, justify="left" if column == "user" else "right")
    for row in board["items"]:
        rank = str(row["rank"]) if row["rank"] is not None else "baseline"
        cells = [
            f"{row['tasks'][t]['success_rate']:.2f}" if t in row["tasks"] else "-" for t in tasks
        ]
        table.add_row(
            rank, row["username"], str(row["submission_id"]), f"{row['score']:.3f}", *cells
        )
    Console(width=max(Console().width, 150)).print(table)
