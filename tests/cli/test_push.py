"""A new participant's path on the embedded default, against a real `manieval serve` with the
registry and Podman it started: register, log in (the engine too), build the policy template
with Podman, `manieval push --wait`; and what `manieval push` says when it cannot. Last, the
getting-started page's commands, run as they are in a fresh virtualenv, to a ranked row."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from server.downloads.artifacts import source_dir
from tests.cli.conftest import Participant, clean_environment, free_port
from tests.cli.push_support import (
    BUILT,
    CHALLENGE,
    TAG,
    VISUAL_CHALLENGE,
    VISUAL_SUITE,
    Embedded,
    build_openpi,
    build_template,
    embedded_service,
)
from tests.web.start_commands import page_commands
from tests.worker.container_fixtures import CONTAINERS_CONF

pytestmark = [pytest.mark.sim, pytest.mark.long]


@pytest.fixture(scope="module")
def embedded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Embedded]:
    more = {VISUAL_CHALLENGE: VISUAL_SUITE}
    with embedded_service(tmp_path_factory.mktemp("push"), more_challenges=more) as service:
        yield service


def registered(embedded: Embedded, name: str) -> tuple[Participant, dict[str, str]]:
    someone = embedded.participant(name)
    someone.register(name)
    env = embedded.engine_env(name)
    r = someone.run("login", "-u", name, "--password-stdin", input=_password(), env=env)
    assert r.exit_code == 0, r.output
    assert f"podman logged in to the registry {embedded.registry} as {name}" in r.output
    return someone, env


def _password() -> str:
    from testkit.factories import PASSWORD

    return PASSWORD + "\n"


def test_a_participant_pushes_the_template_and_it_is_ranked(embedded: Embedded) -> None:
    alice, env = registered(embedded, "alice")
    context = build_template(embedded, f"localhost/alice-policy:{TAG}")
    since = time.time() - 5

    started = time.monotonic()
    r = alice.run(
        "push", f"localhost/alice-policy:{TAG}", "-c", CHALLENGE, "--wait", "--json", env=env
    )
    elapsed = time.monotonic() - started
    assert r.exit_code == 0, r.output
    assert (
        f"pushing localhost/alice-policy:{TAG} to {embedded.registry}/alice/alice-policy:{TAG}"
        in (r.output)
    )
    final = json.loads(r.stdout[r.stdout.index("{") :])
    assert final["state"] == "succeeded", final
    pinned = final["pinned_image"]
    assert pinned.startswith(f"{embedded.registry}/alice/alice-policy@sha256:")
    print(f"push to succeeded: {elapsed:.1f} s")  # the closing note (-s shows it)

    # The same seeds locally, with `manieval evaluate --policy`, score the same episodes.
    out = embedded.work / "local.json"
    local = alice.run(
        "evaluate", "--policy", str(context), "--suite", str(embedded.suite), "--json", str(out)
    )
    assert local.exit_code == 0, local.output
    doc = json.loads(out.read_text())
    expected = [
        (e["seed"], e["success_once"], e["steps"], round(e["episode_return"], 6))
        for c in doc["conditions"]
        for t in c["tasks"]
        for e in t["episodes"]
    ]
    token = json.loads((alice.config_dir / "credentials.json").read_text())["token"]
    with httpx.Client(base_url=embedded.server.url, timeout=30) as http:
        episodes = http.get(
            f"/api/v1/submissions/{final['id']}/episodes",
            headers={"Authorization": f"Bearer {token}"},
        ).json()["items"]
        board = http.get(f"/api/v1/challenges/{CHALLENGE}/leaderboard").json()["items"]
    served = [
        (e["seed"], e["success_once"], e["steps"], round(e["episode_return"], 6)) for e in episodes
    ]
    assert served == expected
    assert [t["success_rate"] for t in final["tasks"]] == [
        t["success_rate"] for c in doc["conditions"] for t in c["tasks"]
    ]
    rows = [(row["username"], row["submission_id"]) for row in board]
    assert [row for row in rows if row[0] == "alice"] == [("alice", final["id"])]

    # The engine's word, not the server's: Podman started a container of the pinned image.
    events = subprocess.run(
        [
            "podman",
            "events",
            "--stream=false",
            "--since",
            str(int(since)),
            "--filter",
            "event=start",
            "--filter",
            "label=manieval.role=policy",
            "--format",
            "{{.Image}}",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert pinned in events.stdout.split(), events.stdout + events.stderr


def test_status_of_a_pushed_submission_names_its_registry_image(embedded: Embedded) -> None:
    bob, env = registered(embedded, "bob")
    build_template(embedded, f"localhost/bob-policy:{TAG}")
    r = bob.run("push", f"localhost/bob-policy:{TAG}", "-c", CHALLENGE, "--name", "walker", env=env)
    assert r.exit_code == 0, r.output
    assert f"{embedded.registry}/bob/walker:{TAG}" in r.output
    assert "follow it: manieval status" in r.output


def test_push_without_an_engine_says_how_to_get_one(embedded: Embedded, tmp_path: Path) -> None:
    someone = embedded.participant("nobody")
    r = someone.run("push", "my-policy", "-c", CHALLENGE, env={"PATH": str(tmp_path)})
    assert r.exit_code == 21, r.output
    assert "no container engine here" in r.output
    assert "apt-get install -y podman" in r.output


def test_push_of_an_image_that_is_not_there_exits_22(embedded: Embedded) -> None:
    carol, env = registered(embedded, "carol")
    r = carol.run("push", f"localhost/never-built:{TAG}", "-c", CHALLENGE, env=env)
    assert r.exit_code == 22, r.output
    assert f"podman has no image localhost/never-built:{TAG}" in r.output
    assert f"podman build -t localhost/never-built:{TAG}" in r.output


def test_push_to_a_registry_that_is_down_exits_24(embedded: Embedded) -> None:
    dave, env = registered(embedded, "dave")
    build_template(embedded, f"localhost/dave-policy:{TAG}")
    closed = f"127.0.0.1:{free_port()}"
    r = dave.run(
        "push", f"localhost/dave-policy:{TAG}", "-c", CHALLENGE, "--registry", closed, env=env
    )
    assert r.exit_code == 24, r.output
    assert f"the registry {closed} does not answer" in r.output


def test_push_with_a_revoked_engine_login_is_refused(embedded: Embedded) -> None:
    erin, env = registered(embedded, "erin")
    build_template(embedded, f"localhost/erin-policy:{TAG}")
    saved = json.loads((erin.config_dir / "credentials.json").read_text())
    with httpx.Client(base_url=embedded.server.url, timeout=30) as http:
        fresh = http.post(
            "/api/v1/auth/token",
            json={"login": "erin", "password": _password().strip(), "name": "second"},
        ).json()["token"]
        r = http.delete(
            f"/api/v1/tokens/{saved['token_id']}", headers={"Authorization": f"Bearer {fresh}"}
        )
        assert r.status_code in (200, 204), r.text
    # The engine still holds the revoked token: the registry refuses it.
    r = erin.run(
        "push",
        f"localhost/erin-policy:{TAG}",
        "-c",
        CHALLENGE,
        env={**env, "MANIEVAL_TOKEN": fresh},
    )
    assert r.exit_code == 23, r.output
    assert "the registry refused the push" in r.output
    assert "run manieval login again" in r.output


def test_another_users_image_cannot_be_submitted(embedded: Embedded) -> None:
    frank, env = registered(embedded, "frank")
    build_template(embedded, f"localhost/frank-policy:{TAG}")
    r = frank.run("push", f"localhost/frank-policy:{TAG}", "-c", CHALLENGE, "--json", env=env)
    assert r.exit_code == 0, r.output
    pinned = json.loads(r.stdout[r.stdout.index("{") :])["pinned_image"]
    grace, genv = registered(embedded, "grace")
    r = grace.run("submit", pinned, "-c", CHALLENGE, env=genv)
    assert r.exit_code == 16, r.output
    assert "grace/" in r.output


def test_an_openpi_server_image_is_pushed_and_ranked_on_the_visual_track(
    embedded: Embedded,
) -> None:
    olga, env = registered(embedded, "olga")
    local = f"localhost/olga-openpi:{TAG}"
    build_openpi(embedded, local)
    r = olga.run("push", local, "-c", VISUAL_CHALLENGE, "--wait", "--json", env=env)
    assert r.exit_code == 0, r.output
    final = json.loads(r.stdout[r.stdout.index("{") :])
    assert final["state"] == "succeeded", final
    assert final["pinned_image"].startswith(f"{embedded.registry}/olga/olga-openpi@sha256:")
    token = json.loads((olga.config_dir / "credentials.json").read_text())["token"]
    with httpx.Client(base_url=embedded.server.url, timeout=30) as http:
        episodes = http.get(
            f"/api/v1/submissions/{final['id']}/episodes",
            headers={"Authorization": f"Bearer {token}"},
        ).json()["items"]
        board = http.get(f"/api/v1/challenges/{VISUAL_CHALLENGE}/leaderboard").json()["items"]
    # Every step answered by the server in the image, through the bridge.
    assert [(e["failure"], e["steps"]) for e in episodes] == [(None, 12)], episodes
    assert [(row["username"], row["submission_id"]) for row in board] == [("olga", final["id"])]


# What the participant's slim virtualenv must not hold: the server's, the worker's and the
# simulator's packages.
SERVER_SIDE = ("fastapi", "sqlalchemy", "celery", "torch", "mani_skill", "sapien", "server")
OFFLINE_INDEX = "file:///opt/pypi/simple"  # this machine's copy of the index: no internet


def terminal_env(embedded: Embedded, home: Path, *, simulator: bool) -> dict[str, str]:
    """A participant's terminal: nothing of this test's virtualenv on PATH or PYTHONPATH (the
    page's `manieval` is the one it installs), unless the step needs the simulator, which the
    page says the whole of ManiEval brings (this virtualenv, with the sources under test)."""
    env = clean_environment()
    project_bin = str(Path(sys.executable).parent)
    if simulator:
        env["PATH"] = os.pathsep.join([project_bin, env.get("PATH", "")])
    else:
        for name in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME"):
            env.pop(name, None)
        paths = env.get("PATH", "").split(os.pathsep)
        env["PATH"] = os.pathsep.join(p for p in paths if p != project_bin)
    return env | {
        "MANIEVAL_CONFIG_DIR": str(home / "config"),
        "PIP_INDEX_URL": OFFLINE_INDEX,
        "COLUMNS": "200",
        **embedded.engine_env("starter"),
        "CONTAINERS_CONF": str(CONTAINERS_CONF),
    }


def test_the_getting_started_page_takes_a_fresh_virtualenv_to_a_ranked_submission(
    embedded: Embedded, tmp_path: Path
) -> None:
    from testkit.factories import PASSWORD

    page = httpx.get(f"{embedded.server.url}/challenges/{CHALLENGE}/start", timeout=30)
    assert page.status_code == 200, page.text
    blocks = page_commands(page.text)
    assert [b.step for b in blocks] == [
        "install",
        "account",
        "template",
        "simulator",
        "evaluate",
        "build",
        "push",
        "board",
    ]
    # The base comes from the service's registry, published there at its start, pinned.
    build = next(b for b in blocks if b.step == "build")
    assert f"--build-arg BASE={embedded.registry}/manieval/policy-base@sha256:" in build.lines[0]
    # The page's tag, my-policy:v1, made this session's own (sessions at once share the image
    # store), and removed with the module's images.
    BUILT.append(f"localhost/my-policy:{TAG}")
    sourced: list[str] = []  # `. manieval-env/bin/activate`: it holds for the lines after it
    said: dict[str, str] = {}
    for block in blocks:
        simulator = block.needs == "simulator"
        env = terminal_env(embedded, tmp_path, simulator=simulator)
        for line in block.lines:
            line = line.replace("NAME", "starter")  # the placeholder the page asks to fill
            line = line.replace("my-policy:v1", f"my-policy:{TAG}")
            if block.needs == "source-install" and not line.startswith(("curl ", "tar ")):
                # `make install-evaluator` of the source (a part of this suite's own install)
                # is what gives the simulator's steps this virtualenv: the source is downloaded
                # and unpacked, and the lines name its Makefile's target and its virtualenv.
                source = tmp_path / source_dir()
                assert line in (
                    f"make -C {source_dir()} install-evaluator",
                    f". {source_dir()}/.venv/bin/activate",
                )
                assert "\ninstall-evaluator:\n" in (source / "Makefile").read_text()
                assert "\nVENV := .venv\n" in (source / "Makefile").read_text()
                continue
            answers = {"register": 2, "login": 1}.get(line.split()[1], 0)
            done = subprocess.run(
                [
                    "bash",
                    "-euo",
                    "pipefail",
                    "-c",
                    "\n".join([*([] if simulator else sourced), line]),
                ],
                cwd=tmp_path,
                env=env,
                input=(PASSWORD + "\n") * answers if line.startswith("manieval") else "",
                capture_output=True,
                text=True,
                timeout=900,
                start_new_session=True,  # no terminal: the password prompts read stdin
            )
            assert done.returncode == 0, f"$ {line}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
            said[block.step] = said.get(block.step, "") + done.stdout + done.stderr
            if line.startswith(". ") and not simulator:
                sourced.append(line)
        if block.step == "install":
            venv = tmp_path / "manieval-env" / "bin" / "python"
            check = (
                f"import importlib.util as u; print([m for m in {SERVER_SIDE!r} if u.find_spec(m)])"
            )
            found = subprocess.run(
                [str(venv), "-c", check],
                cwd=tmp_path,
                env=terminal_env(embedded, tmp_path, simulator=False),
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert found.stdout.strip() == "[]", found.stdout + found.stderr

    assert "succeeded" in said["push"], said["push"]
    assert "starter" in said["board"], said["board"]
    with httpx.Client(base_url=embedded.server.url, timeout=30) as http:
        board = http.get(f"/api/v1/challenges/{CHALLENGE}/leaderboard").json()["items"]
    ranks = [row["rank"] for row in board if row["username"] == "starter"]
    assert len(ranks) == 1, board
    assert ranks[0] is not None, board  # ranked, not a baseline
