"""A challenge's own evaluator image: `manieval challenge load --evaluator-image`, kept on the
challenge, shown to admins by the challenge API, handed to the worker with each claim."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from evaluator import packages
from manieval.cli import app
from server.challenges.evaluator_image import WORKERS_OWN, evaluator_image_note
from server.kit.errors import Invalid
from server.models import Challenge
from server.submissions.work import assignment, claim_next
from testkit.factories import SUITE, make_challenge, make_user, queue_submission, token_for
from tests.server.test_cli import PACKAGED_SUITE, db_session

runner = CliRunner()
LAB = "registry.example.org/lab/evaluator-lab-tasks@sha256:" + "1a" * 32
LAB_NEXT = "registry.example.org/lab/evaluator-lab-tasks@sha256:" + "2b" * 32


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    return tmp_path


def load(*args: str) -> tuple[int, str]:
    r = runner.invoke(app, ["challenge", "load", "--unverified", *args])
    return r.exit_code, " ".join(r.output.split())


def stored_image(data: Path) -> str | None:
    with db_session(data) as db:
        return db.scalars(select(Challenge)).one().evaluator_image


def test_load_names_the_image_keeps_it_on_reload_and_goes_back_to_the_workers_own(
    env: Path,
) -> None:
    code, out = load(str(SUITE), "--evaluator-image", LAB)
    assert code == 0, out
    assert f"evaluator image {LAB}" in out
    # The embedded default runs no evaluator image, and says so.
    assert "the embedded worker evaluates in this service's own environment" in out
    assert stored_image(env) == LAB
    code, out = load(str(SUITE), "--quota-per-day", "9")  # a reload for another reason
    assert code == 0, out
    assert stored_image(env) == LAB
    code, out = load(str(SUITE), "--evaluator-image", WORKERS_OWN)
    assert code == 0, out
    assert stored_image(env) is None
    assert "evaluator image" not in out


@pytest.mark.parametrize(
    ("reference", "message"),
    [
        (
            "registry.example.org/lab/evaluator-lab-tasks:0.1.0",
            "names a tag, which can move: pin it by digest "
            "(registry.example.org/lab/evaluator-lab-tasks@sha256:<digest>",
        ),
        ("registry.example.org/Lab/evaluator@sha256:" + "1a" * 32, "must be lowercase"),
        ("registry.example.org/lab/evaluator@sha256:1a2b", "64 lowercase hex digits"),
        ("registry.example.org/lab/evaluator@sha512:" + "1a" * 64, "not pinned by a sha256"),
        ("lab evaluator", "contains whitespace"),
    ],
    ids=["tag", "uppercase", "short-digest", "sha512", "blank"],
)
def test_load_refuses_an_image_not_pinned_by_digest_saying_why(
    env: Path, reference: str, message: str
) -> None:
    code, out = load(str(SUITE), "--evaluator-image", reference)
    assert code == 1
    assert "error: evaluator image:" in out
    assert message in out
    with db_session(env) as db:
        assert db.scalars(select(Challenge)).all() == []  # nothing loaded


def test_a_reload_whose_task_packages_changed_must_name_an_image_again(
    env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(packages, "simulator_installed", lambda: False)  # a control plane
    suite = env / "lab.yaml"
    base = PACKAGED_SUITE.read_text()
    suite.write_text(base + 'package_versions: {manieval_test_tasks: "0.1.0"}\n')
    code, out = load(str(suite), "--evaluator-image", LAB)
    assert code == 0, out
    suite.write_text(base + 'package_versions: {manieval_test_tasks: "0.2.0"}\n')
    code, out = load(str(suite))
    assert code == 1
    assert (
        f"the challenge's evaluator image {LAB} was given for its task packages "
        "manieval_test_tasks 0.1.0, and the suite now has manieval_test_tasks 0.2.0"
    ) in out
    assert stored_image(env) == LAB  # refused: nothing changed
    code, out = load(str(suite), "--evaluator-image", LAB_NEXT)
    assert code == 0, out
    assert stored_image(env) == LAB_NEXT


def test_the_note_says_which_workers_run_the_image() -> None:
    inline = evaluator_image_note(LAB, queue="inline")
    assert "runs no evaluator image" in inline
    assert "task packages must be installed here" in inline
    celery = evaluator_image_note(LAB, queue="celery")
    assert "listed in their MANIEVAL_EVALUATOR_IMAGES" in celery
    assert "docker executor evaluate in their own environment and ignore it" in celery


def test_the_service_refuses_a_tag_with_its_field(sessions: sessionmaker[Session]) -> None:
    with sessions() as db, pytest.raises(Invalid) as refused:
        make_challenge(db, evaluator_image="registry.example.org/lab/evaluator:1")
    assert "names a tag" in refused.value.fields["evaluator_image"]


def test_admins_see_the_image_in_the_challenge_api_and_no_one_else_does(
    client: TestClient, sessions: sessionmaker[Session]
) -> None:
    with sessions() as db:
        make_challenge(db, evaluator_image=LAB)
        make_user(db, "alice")
        make_user(db, "organizer", admin=True)
    url = "/api/v1/challenges/server-tiny"
    assert client.get(url, headers=token_for(client, "organizer")).json()["evaluator_image"] == LAB
    assert client.get(url, headers=token_for(client, "alice")).json()["evaluator_image"] is None
    assert client.get(url).json()["evaluator_image"] is None


@pytest.mark.parametrize("image", [LAB, None], ids=["its-own", "the-workers-own"])
def test_the_claimed_work_carries_the_challenges_image(
    sessions: sessionmaker[Session], image: str | None
) -> None:
    with sessions() as db:
        challenge = make_challenge(db, **({"evaluator_image": image} if image else {}))
        submission = queue_submission(db, make_user(db, "alice"), challenge)
        db.commit()
        claimed = claim_next(db, worker="w1", max_running_per_user=2)
        assert claimed == (submission.id, 1)
        handed = assignment(db, submission_id=submission.id, attempt=1, seed_secret=b"s" * 32)
    assert handed.evaluator_image == image
