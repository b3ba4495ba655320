"""The participant commands end to end against a real server: the journey and every error."""

from __future__ import annotations

import json
import os
import re
import secrets
import signal
import stat
import subprocess
import time
from collections.abc import Iterator
from datetime import datetime, timedelta, timezone
from pathlib import Path

import httpx
import pytest

from manieval.errors import ExitCode
from testkit.factories import PASSWORD
from tests.cli.conftest import LiveServer, Participant, participant, running_server

pytestmark = pytest.mark.sim
ACCEPTED = re.compile(r"submission (\d+) accepted")
TERMINAL = {"TTY_COMPATIBLE": "1", "TERM": "xterm-256color"}  # rich: treat the output as a tty


def accepted_id(output: str) -> int:
    found = ACCEPTED.search(output)
    assert found is not None, output
    return int(found[1])


def read_until(process: subprocess.Popen[str], pattern: str) -> list[str]:
    """Lines of the process's stderr up to the first that matches `pattern`."""
    assert process.stderr is not None
    lines: list[str] = []
    while not lines or not re.search(pattern, lines[-1]):
        line = process.stderr.readline()
        assert line, f"the command ended before {pattern!r}: {''.join(lines)}"
        lines.append(line)
    return lines


def test_a_participant_registers_submits_follows_compares_and_logs_out(
    live: LiveServer, tmp_path: Path
) -> None:
    alice = Participant(live.url, tmp_path / "config")
    r = alice.run(
        "register", "-u", "alice", "--email", "alice@example.org", input=f"{PASSWORD}\n" * 2
    )
    assert r.exit_code == 0, r.output
    assert "manieval login -u alice" in r.output
    r = alice.run("login", "-u", "alice", input=f"{PASSWORD}\n")
    assert r.exit_code == 0, r.output
    token_file = tmp_path / "config" / "credentials.json"
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    assert stat.S_IMODE(token_file.parent.stat().st_mode) == 0o700
    saved = json.loads(token_file.read_text())
    assert saved["server"] == live.url
    assert saved["username"] == "alice"
    assert saved["token"].startswith("mev_")

    r = alice.run("challenges")
    assert r.exit_code == 0, r.output
    assert "server-tiny" in r.stdout
    r = alice.run("challenges", "--json")
    assert {c["slug"] for c in json.loads(r.stdout)} == {
        "server-tiny",
        "server-long",
        "server-quota",
        "server-gpu",
    }

    r = alice.run(
        "submit", "local:scripted", "-c", "server-tiny", "--description", "first", "--wait"
    )
    assert r.exit_code == ExitCode.OK, r.output
    sid = accepted_id(r.stderr)
    assert f"submission {sid}: succeeded" in r.stderr
    assert "PickCube-v1" in r.stdout
    assert "nominal" in r.stdout
    assert "obs_noise" in r.stdout

    r = alice.run("status")
    assert r.exit_code == 0, r.output
    assert re.search(rf"\b{sid}\b.*server-tiny.*succeeded", r.stdout)
    r = alice.run("status", str(sid), "--json")
    detail = json.loads(r.stdout)
    assert (detail["state"], detail["description"], len(detail["tasks"])) == (
        "succeeded",
        "first",
        2,
    )
    r = alice.run("status", str(sid))
    assert "timeline" in r.stdout
    assert "local:scripted" in r.stdout
    r = alice.run("logs", str(sid))
    assert r.exit_code == 0, r.output
    # The scripted policy prints nothing: an empty log of an ended run is not "yet" to come.
    assert f"submission {sid} (attempt 1) ended succeeded" in r.stderr
    assert "yet" not in r.stderr

    r = alice.run("leaderboard", "server-tiny", "--json")
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)["items"]
    assert [(row["username"], row["submission_id"]) for row in rows] == [("alice", sid)]
    r = alice.run("leaderboard", "server-tiny", "--csv")
    lines = r.stdout.splitlines()
    assert lines[0].startswith("rank,username,")
    assert lines[1].split(",")[:2] == ["1", "alice"]
    r = alice.run("leaderboard", "server-tiny")
    assert "alice" in r.stdout

    r = alice.run(
        "submit", "local:random", "-c", "server-long", "--phase", "test", "--private", "--json",
        "--method", "Random baseline", "--code-url", "https://example.org/random",
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    queued = json.loads(r.stdout)
    assert (queued["state"], queued["public"], queued["phase"]) == ("queued", False, "test")
    assert (queued["method"], queued["paper_url"]) == ("Random baseline", None)
    assert queued["code_url"] == "https://example.org/random"
    r = alice.run("submit", "local:random", "-c", "server-long", "--paper-url", "arxiv.org/x")
    assert r.exit_code == ExitCode.INVALID, r.output
    assert "paper_url" in r.output
    long_id = queued["id"]
    r = alice.run("cancel", str(long_id))
    assert r.exit_code == 0, r.output
    assert "cancelled" in r.output
    assert json.loads(alice.run("status", str(long_id), "--json").stdout)["state"] == "cancelled"
    r = alice.run("cancel", str(long_id))
    assert r.exit_code == ExitCode.CONFLICT
    assert "already ended" in r.output

    r = alice.run("logout")
    assert r.exit_code == 0, r.output
    assert "revoked" in r.output
    assert not token_file.exists()
    me = httpx.get(f"{live.url}/api/v1/me", headers={"Authorization": f"Bearer {saved['token']}"})
    assert me.status_code == 401
    assert alice.run("status").exit_code == ExitCode.NOT_LOGGED_IN


def test_wait_exits_1_when_the_policy_fails_and_its_log_says_why(
    live: LiveServer, tmp_path: Path
) -> None:
    bob = participant(live, tmp_path, "bob")
    r = bob.run("submit", "local:crasher", "-c", "server-tiny", "--wait")
    assert r.exit_code == ExitCode.FAILED, r.output
    sid = accepted_id(r.stderr)
    assert r.stderr.count("exit code 3") == 1  # the reason, said once
    assert f"manieval logs {sid}" in r.stderr
    r = bob.run("logs", str(sid))
    assert r.exit_code == 0, r.output
    assert "out of luck" in r.stdout


def test_wait_on_a_terminal_draws_a_live_progress_display(live: LiveServer, tmp_path: Path) -> None:
    paul = participant(live, tmp_path, "paul")
    r = paul.run("submit", "local:scripted", "-c", "server-tiny", "--wait", env=TERMINAL)
    assert r.exit_code == ExitCode.OK, r.output
    assert "episodes" in r.stderr
    assert "\x1b[" in r.stderr  # drawn with terminal control sequences
    assert "PickCube-v1" in r.stdout


@pytest.mark.parametrize("started", ["from a terminal", "in the background"])
def test_ctrl_c_stops_waiting_without_cancelling_and_says_how_to_resume(
    live: LiveServer, tmp_path: Path, started: str
) -> None:
    carol = participant(live, tmp_path, f"carol-{secrets.token_hex(4)}")  # one each, run again
    waiting = carol.spawn(
        "submit",
        "local:random",
        "-c",
        "server-long",
        "--wait",
        sigint_ignored=started == "in the background",  # SIGINT still stops it (docs/cli.md)
    )
    sid = accepted_id("".join(read_until(waiting, "accepted")))
    read_until(waiting, rf"submission {sid}: ")  # the wait loop is showing the state
    waiting.send_signal(signal.SIGINT)
    _, err = waiting.communicate(timeout=60)
    assert waiting.returncode == ExitCode.INTERRUPTED, err
    assert f"manieval status {sid} --wait" in err
    assert f"manieval cancel {sid}" in err
    assert "Traceback" not in err
    state = json.loads(carol.run("status", str(sid), "--json").stdout)["state"]
    assert state in ("queued", "launching", "running")
    assert carol.run("cancel", str(sid)).exit_code == 0


def test_wait_exits_5_when_the_submission_is_cancelled_meanwhile(
    live: LiveServer, tmp_path: Path
) -> None:
    dave = participant(live, tmp_path, "dave")
    waiting = dave.spawn("submit", "local:random", "-c", "server-long", "--wait")
    sid = accepted_id("".join(read_until(waiting, "accepted")))
    assert dave.run("cancel", str(sid)).exit_code == 0
    _, err = waiting.communicate(timeout=120)
    assert waiting.returncode == ExitCode.CANCELLED, err
    assert f"submission {sid}: cancelled" in err


# Errors ----------------------------------------------------------------------------------------


def test_an_unreachable_server_is_named_with_a_hint(live: LiveServer, tmp_path: Path) -> None:
    closed = f"http://127.0.0.1:{live.closed_port}"
    r = Participant(closed, tmp_path / "config").run("challenges")
    assert r.exit_code == ExitCode.UNREACHABLE
    assert closed in r.stderr
    assert "--server" in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)


def test_a_server_url_with_a_wrong_path_is_not_a_manieval_server(
    live: LiveServer, tmp_path: Path
) -> None:
    # The API's own path given twice answers JSON 404s (a page path answers HTML ones): both
    # are a wrong --server, not an unknown challenge or submission.
    for url in (f"{live.url}/api/v1", f"{live.url}/no-such-prefix"):
        wrong = Participant(url, tmp_path / "config")
        for args in (["challenges"], ["leaderboard", "server-tiny"], ["status", "1"]):
            r = wrong.run(*args)
            assert r.exit_code == ExitCode.SERVER_ERROR, (url, args, r.output)
            assert "ManiEval server" in r.stderr


def test_a_wrong_password_is_bad_credentials_and_saves_nothing(
    live: LiveServer, tmp_path: Path
) -> None:
    erin = Participant(live.url, tmp_path / "config")
    erin.register("erin")
    r = erin.run("login", "-u", "erin", "--password-stdin", input="not the password at all\n")
    assert r.exit_code == ExitCode.BAD_CREDENTIALS
    assert "wrong username, email or password" in r.stderr
    assert not (tmp_path / "config" / "credentials.json").exists()


def test_commands_that_need_a_login_say_so(live: LiveServer, tmp_path: Path) -> None:
    nobody = Participant(live.url, tmp_path / "config")
    for args in (["submit", "local:random", "-c", "server-tiny"], ["status"], ["logs", "1"]):
        r = nobody.run(*args)
        assert r.exit_code == ExitCode.NOT_LOGGED_IN, r.output
        assert "manieval login" in r.stderr


def test_a_revoked_token_asks_to_log_in_again(live: LiveServer, tmp_path: Path) -> None:
    frank = participant(live, tmp_path, "frank")
    saved = json.loads((tmp_path / "config" / "credentials.json").read_text())
    revoked = httpx.delete(
        f"{live.url}/api/v1/tokens/{saved['token_id']}",
        headers={"Authorization": f"Bearer {saved['token']}"},
    )
    assert revoked.status_code == 200
    r = frank.run("status")
    assert r.exit_code == ExitCode.TOKEN_REJECTED
    assert "run manieval login" in r.stderr


def test_logging_in_again_revokes_the_replaced_token(live: LiveServer, tmp_path: Path) -> None:
    nina = participant(live, tmp_path, "nina")
    token_file = tmp_path / "config" / "credentials.json"
    first = json.loads(token_file.read_text())["token"]
    nina.login("nina")
    second = json.loads(token_file.read_text())["token"]
    me = f"{live.url}/api/v1/me"
    assert httpx.get(me, headers={"Authorization": f"Bearer {first}"}).status_code == 401
    assert httpx.get(me, headers={"Authorization": f"Bearer {second}"}).status_code == 200


def test_a_token_that_cannot_be_saved_is_revoked_and_said(live: LiveServer, tmp_path: Path) -> None:
    omar = Participant(live.url, tmp_path / "not-a-directory")
    omar.config_dir.write_text("a file where the config directory should be")
    omar.register("omar")
    r = omar.run("login", "-u", "omar", "--password-stdin", input=PASSWORD + "\n")
    assert r.exit_code == 12, r.output
    assert "cannot save the API token" in r.output
    assert "Traceback" not in r.output
    fresh = httpx.post(
        f"{live.url}/api/v1/auth/token", json={"login": "omar", "password": PASSWORD}
    ).json()
    tokens = httpx.get(
        f"{live.url}/api/v1/tokens", headers={"Authorization": f"Bearer {fresh['token']}"}
    ).json()
    assert len(tokens) == 2  # the CLI's, and the one just made to look
    assert [t["id"] for t in tokens if t["revoked_at"] is None] == [fresh["id"]]


def test_logout_works_when_the_server_is_gone_and_says_so(tmp_path: Path) -> None:
    with running_server(tmp_path / "gone", challenges=False) as server:
        olga = participant(server, tmp_path, "olga")
    r = olga.run("logout")
    assert r.exit_code == 0, r.output
    assert "could not be reached" in r.stderr
    assert "still valid" in r.stderr
    assert not (tmp_path / "config" / "credentials.json").exists()


def test_a_token_in_the_environment_needs_no_login_file(live: LiveServer, tmp_path: Path) -> None:
    grace = participant(live, tmp_path, "grace")
    token = json.loads((tmp_path / "config" / "credentials.json").read_text())["token"]
    elsewhere = Participant(live.url, tmp_path / "ci-config")
    r = elsewhere.run("status", env={"MANIEVAL_TOKEN": token})
    assert r.exit_code == 0, r.output
    assert grace.run("status").exit_code == 0


@pytest.fixture
def local_zone() -> Iterator[timezone]:
    """The process's local time zone set to UTC+05:30, named XYZ."""
    old = os.environ.get("TZ")
    os.environ["TZ"] = "XYZ-5:30"
    time.tzset()
    yield timezone(timedelta(hours=5, minutes=30))
    if old is None:
        del os.environ["TZ"]
    else:
        os.environ["TZ"] = old
    time.tzset()


def test_quota_exceeded_says_when_it_resets_in_local_time(
    live: LiveServer, tmp_path: Path, local_zone: timezone
) -> None:
    heidi = participant(live, tmp_path, "heidi")
    assert heidi.run("submit", "local:random", "-c", "server-quota").exit_code == 0
    r = heidi.run("submit", "local:random", "-c", "server-quota")
    assert r.exit_code == ExitCode.QUOTA_EXCEEDED, r.output
    token = json.loads((tmp_path / "config" / "credentials.json").read_text())["token"]
    quota = httpx.get(
        f"{live.url}/api/v1/challenges/server-quota",
        headers={"Authorization": f"Bearer {token}"},
    ).json()["my_quota"]
    resets = datetime.fromisoformat(quota["resets_at"]).astimezone(local_zone)
    assert f"{resets:%Y-%m-%d %H:%M:%S} XYZ" in r.stderr
    assert "quota" in r.stderr


def test_a_bad_image_reference_shows_the_servers_field_message(
    live: LiveServer, tmp_path: Path
) -> None:
    ivan = participant(live, tmp_path, "ivan")
    r = ivan.run("submit", "Not A Reference", "-c", "server-tiny")
    assert r.exit_code == ExitCode.INVALID
    assert "invalid image: image reference contains whitespace" in r.stderr
    r = ivan.run("submit", "local:nothing-like-it", "-c", "server-tiny")
    assert r.exit_code == ExitCode.INVALID
    assert "image: one of: crasher, random, scripted" in r.stderr


def test_a_challenge_that_needs_gpus_this_service_lacks_is_refused_with_the_reason(
    live: LiveServer, tmp_path: Path
) -> None:
    kate = participant(live, tmp_path, "kate")
    r = kate.run("submit", "local:random", "-c", "server-gpu")
    assert r.exit_code == ExitCode.CONFLICT, r.output
    assert "error: this challenge asks for 1 GPU per policy, and this service has none" in r.stderr
    assert "MANIEVAL_POLICY_GPUS" in r.stderr


def test_unknown_challenges_and_submissions_are_not_found(live: LiveServer, tmp_path: Path) -> None:
    judy = participant(live, tmp_path, "judy")
    for args, message in [
        (["submit", "local:random", "-c", "no-such"], "no challenge 'no-such'"),
        (["leaderboard", "no-such"], "no challenge 'no-such'"),
        (["status", "999999"], "no submission 999999"),
        (["cancel", "999999"], "no submission 999999"),
    ]:
        r = judy.run(*args)
        assert r.exit_code == ExitCode.NOT_FOUND, r.output
        assert message in r.stderr


def test_a_registry_outage_is_a_server_error_to_retry(live: LiveServer, tmp_path: Path) -> None:
    kim = participant(live, tmp_path, "kim")
    r = kim.run("submit", f"127.0.0.1:{live.closed_port}/team/policy:v1", "-c", "server-tiny")
    assert r.exit_code == ExitCode.SERVER_ERROR, r.output
    assert "HTTP 503" in r.stderr
    assert "try again later" in r.stderr


def test_rate_limits_say_when_to_try_again(tmp_path: Path) -> None:
    strict = {"MANIEVAL_REGISTER_RATE": "1/hour"}
    with running_server(tmp_path / "strict", challenges=False, extra=strict) as server:
        someone = Participant(server.url, tmp_path / "config")
        someone.register("lena")
        r = someone.run(
            "register",
            "-u",
            "mona",
            "--email",
            "m@example.org",
            "--password-stdin",
            input=PASSWORD + "\n",
        )
    assert r.exit_code == ExitCode.RATE_LIMITED, r.output
    assert re.search(r"try again in \d+ (min|h)", r.stderr)


def test_bad_options_are_usage_errors(tmp_path: Path) -> None:
    nobody = Participant("http://127.0.0.1:9", tmp_path / "config")
    assert nobody.run("challenges", "--server", "ftp://example.org").exit_code == ExitCode.USAGE
    assert nobody.run("leaderboard", "x", "--json", "--csv").exit_code == ExitCode.USAGE
    assert nobody.run("status", "--wait").exit_code == ExitCode.USAGE
