"""`manieval trajectories` against a real server and worker: a dev-phase submission's files
download, h5py reads ManiSkill's keys in them, and ManiSkill's replay tool gets every
episode's success back."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import h5py
import httpx
import pytest

from manieval.errors import ExitCode
from tests.cli.conftest import LiveServer, participant

pytestmark = pytest.mark.sim
ACCEPTED = re.compile(r"submission (\d+) accepted")


def test_a_dev_phase_submissions_trajectories_download_and_replay_to_its_successes(
    live: LiveServer, tmp_path: Path
) -> None:
    alice = participant(live, tmp_path, "alice")
    r = alice.run("submit", "local:scripted", "-c", "server-tiny", "--wait")
    assert r.exit_code == ExitCode.OK, r.output
    found = ACCEPTED.search(r.stderr)
    assert found is not None, r.output
    sid = int(found[1])
    out = tmp_path / "trajectories"
    r = alice.run("trajectories", str(sid), "-o", str(out))
    assert r.exit_code == 0, r.output
    stems = ["nominal--PickCube-v1", "obs_noise--PickCube-v1"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{s}.{ext}" for s in stems for ext in ("h5", "json")
    )
    token = json.loads((tmp_path / "config" / "credentials.json").read_text())["token"]
    episodes = httpx.get(
        f"{live.url}/api/v1/submissions/{sid}/episodes",
        headers={"Authorization": f"Bearer {token}"},
        params={"per_page": 100},
    ).json()["items"]
    for stem in stems:
        condition = stem.split("--")[0]
        mine = sorted(
            (e for e in episodes if e["condition"] == condition), key=lambda e: e["index"]
        )
        with h5py.File(out / f"{stem}.h5", "r") as f:
            assert sorted(f) == [f"traj_{i}" for i in range(len(mine))]
            for i, episode in enumerate(mine):
                traj = f[f"traj_{i}"]
                assert {"actions", "env_states", "success", "terminated", "truncated"} <= set(traj)
                assert len(traj["actions"]) == episode["steps"]
        subprocess.run(
            [
                sys.executable,
                "-m",
                "mani_skill.trajectory.replay_trajectory",
                "--traj-path",
                str(out / f"{stem}.h5"),
                "--save-traj",
                "--allow-failure",
            ],
            check=True,
            capture_output=True,
            timeout=600,
        )
        (replayed,) = out.glob(f"{stem}.*.json")
        replay = [bool(e["success"]) for e in json.loads(replayed.read_text())["episodes"]]
        assert replay == [e["success_once"] for e in mine]


def test_a_submission_without_trajectories_is_reported_as_such(
    live: LiveServer, tmp_path: Path
) -> None:
    bob = participant(live, tmp_path, "bob")
    r = bob.run("submit", "local:random", "-c", "server-long", "--json")
    assert r.exit_code == 0, r.output
    sid = json.loads(r.stdout)["id"]
    r = bob.run("trajectories", str(sid), "-o", str(tmp_path / "none"))
    assert r.exit_code == ExitCode.NOT_FOUND, r.output
    assert f"submission {sid} has no recorded trajectories" in r.output
    bob.run("cancel", str(sid))
