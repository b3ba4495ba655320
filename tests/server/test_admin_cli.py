"""The organizer's `manieval admin` commands against a real (SQLite) data directory: each
action recorded as the command line's login."""

from __future__ import annotations

import csv
import getpass
import io
import json
from pathlib import Path

import jwt
import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload
from typer.testing import CliRunner

from manieval.cli import app
from server import audit
from server.kit.db import make_engine, session_factory
from server.models import Challenge, State, Submission
from server.submissions.reports import report_final, report_state
from testkit.factories import SUITE, make_user, queue_submission, result_doc

runner = CliRunner()
ACTOR = f"cli:{getpass.getuser()}"


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    loaded = runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE)])
    assert loaded.exit_code == 0, loaded.output
    return tmp_path


def session(data: Path) -> Session:
    return session_factory(make_engine(f"sqlite:///{data / 'manieval.db'}"))()


@pytest.fixture
def done(env: Path) -> int:
    """Alice's submission on server-tiny, succeeded."""
    with session(env) as db:
        alice = make_user(db, "alice")
        tiny = db.scalar(
            select(Challenge)
            .options(selectinload(Challenge.phases))
            .where(Challenge.slug == "server-tiny")
        )
        assert tiny is not None
        s = queue_submission(db, alice, tiny)
        db.commit()
        assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
        assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
        result = result_doc([True, False], conditions=("nominal", "obs_noise"))
        assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=result)
        db.commit()
        return s.id


def admin(*args: str) -> tuple[int, str]:
    r = runner.invoke(app, ["admin", *args])
    return r.exit_code, r.output


def test_moderation_commands_need_a_reason_and_are_recorded_as_the_command_line(
    env: Path, done: int
) -> None:
    code, said = admin("disqualify", str(done))
    assert code == 1
    assert "say why: a reason is required" in said
    code, said = admin("hide", "999999", "--reason", "x")
    assert code == 1
    assert "no submission 999999" in said
    assert admin("disqualify", str(done), "--reason", "seed leak")[0] == 0
    assert admin("reinstate", str(done))[0] == 0
    assert admin("hide", str(done), "--reason", "duplicate")[0] == 0
    with session(env) as db:
        s = db.get(Submission, done)
        assert s is not None
        assert (s.hidden, s.disqualified, s.moderation_reason) == (True, False, "duplicate")
    assert admin("unhide", str(done), "--reason", "not one")[0] == 0
    code, said = admin("rerun", str(done), "--reason", "flaky node")
    assert code == 0
    assert f"submission {done}: queued again as attempt 2" in said
    assert admin("rerun", str(done))[0] == 1  # it has not ended
    with session(env) as db:
        records = audit.records(db, target_kind="submission")
        assert [(r.action, r.actor, r.reason) for r in records] == [
            ("submission.rerun", ACTOR, "flaky node"),
            ("submission.unhide", ACTOR, "not one"),
            ("submission.hide", ACTOR, "duplicate"),
            ("submission.reinstate", ACTOR, ""),
            ("submission.disqualify", ACTOR, "seed leak"),
        ]


def test_audit_prints_the_records_newest_first_and_pages(env: Path, done: int) -> None:
    assert admin("disqualify", str(done), "--reason", "seed leak")[0] == 0
    closed = runner.invoke(app, ["challenge", "close", "server-tiny", "test"])
    assert closed.exit_code == 0, closed.output
    code, said = admin("audit", "--challenge", "server-tiny")
    assert code == 0
    lines = [line for line in said.splitlines() if "\t" in line]  # the records, not notes
    assert "\tphase.close phase " in lines[0]
    assert (
        f"\t{ACTOR}\tsubmission.disqualify submission {done} [server-tiny]: seed leak" in lines[1]
    )
    code, said = admin("audit", "--limit", "1")
    assert "phase.close" in said
    assert "submission.disqualify" not in said
    assert "older: --before-id" in said
    assert admin("audit", "--challenge", "nope")[0] == 1


def test_export_writes_every_submission_as_csv_or_json(env: Path, done: int) -> None:
    code, said = admin("export", "server-tiny")
    assert code == 0
    (row,) = csv.DictReader(io.StringIO(said))
    assert (row["submission_id"], row["username"], row["score"]) == (str(done), "alice", "0.5000")
    target = env / "export.json"
    code, said = admin(
        "export", "server-tiny", "--phase", "dev", "--format", "json", "--out", str(target)
    )
    assert code == 0
    (item,) = json.loads(target.read_text())
    assert (item["submission_id"], item["state"], item["condition obs_noise"]) == (
        done,
        "succeeded",
        0.5,
    )
    assert admin("export", "server-tiny", "--format", "xml")[0] == 2
    assert admin("export", "nope")[0] == 1


def test_rerun_stuck_says_when_nothing_is_stuck(env: Path, done: int) -> None:
    code, said = admin("rerun-stuck")
    assert code == 0
    assert "nothing is stuck" in said
    assert admin("rerun-stuck", "--challenge", "nope")[0] == 1


def test_publish_token_is_for_the_services_namespace_only_and_recorded(
    env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert admin("publish-token")[0] == 2  # no registry: nothing to publish to
    monkeypatch.setenv("MANIEVAL_REGISTRY_DOMAIN", "127.0.0.1:5000")
    r = runner.invoke(app, ["admin", "publish-token", "--reason", "the base for the challenge"])
    assert r.exit_code == 0, r.output
    claims = jwt.decode(r.stdout.strip(), options={"verify_signature": False})
    assert claims["access"] == [
        {"type": "repository", "name": "manieval/policy-base", "actions": ["pull", "push"]}
    ]
    assert "skopeo copy --dest-registry-token TOKEN" in r.stderr
    code, said = admin("publish-token", "alice/policy")
    assert code == 2
    assert "publishes only under manieval/" in said
    with session(env) as db:
        (record,) = audit.records(db, target_kind="repository")
        assert (record.action, record.actor, record.reason) == (
            "registry.publish_token",
            ACTOR,
            "the base for the challenge",
        )
        assert record.detail == {"repository": "manieval/policy-base"}
