"""`manieval team` against a real server: create, invite, list and accept invitations, show,
leave; errors with the documented exit codes."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from manieval.errors import ExitCode
from tests.cli.conftest import LiveServer, participant

pytestmark = pytest.mark.sim


def test_a_team_is_made_joined_shown_and_left(live: LiveServer, tmp_path: Path) -> None:
    alice = participant(live, tmp_path / "alice", "alice")
    bob = participant(live, tmp_path / "bob", "bob")

    r = alice.run("team", "create", "grasp-lab", "--display-name", "Grasp Lab")
    assert r.exit_code == 0, r.output
    assert "team grasp-lab created" in r.stderr
    r = alice.run("team", "invite", "bob")
    assert r.exit_code == 0, r.output
    found = re.search(r"manieval team accept (\d+)", r.stderr)
    assert found, r.stderr

    r = bob.run("team", "invitations")
    assert r.exit_code == 0, r.output
    assert "Grasp Lab (grasp-lab)" in r.stdout
    r = alice.run("team", "show")
    assert "pending invitations" in r.stdout

    r = bob.run("team", "accept", found[1])
    assert r.exit_code == 0, r.output
    assert "you joined team Grasp Lab (grasp-lab)" in r.stderr
    r = bob.run("team", "show", "--json")
    assert r.exit_code == 0, r.output
    shown = json.loads(r.stdout)
    assert [(m["username"], m["is_admin"]) for m in shown["members"]] == [
        ("alice", True),
        ("bob", False),
    ]
    assert shown["invitations"] is None  # bob is no admin

    r = bob.run("team", "leave")
    assert r.exit_code == 0, r.output
    assert "you left team grasp-lab" in r.stderr
    r = alice.run("team", "leave")
    assert "dissolved" in r.stderr


def test_team_errors_exit_with_their_codes(live: LiveServer, tmp_path: Path) -> None:
    carol = participant(live, tmp_path / "carol", "carol")
    r = carol.run("team", "leave")
    assert r.exit_code == ExitCode.CONFLICT, r.output
    r = carol.run("team", "invite", "nobody")
    assert r.exit_code == ExitCode.CONFLICT, r.output
    assert "you are not in a team" in r.stderr
    r = carol.run("team", "create", "Bad Name")
    assert r.exit_code == ExitCode.INVALID, r.output
    r = carol.run("team", "create", "carols")
    assert r.exit_code == 0, r.output
    r = carol.run("team", "invite", "nobody")
    assert r.exit_code == ExitCode.NOT_FOUND, r.output
    r = carol.run("team", "accept", "999999")  # in a team: told so before any look-up
    assert r.exit_code == ExitCode.CONFLICT, r.output
    assert "you are in team 'carols'" in r.stderr
    r = carol.run("team", "show", "no-such-team")
    assert r.exit_code == ExitCode.NOT_FOUND, r.output
