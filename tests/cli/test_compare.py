"""`manieval compare` against a real server: the paired tables, the verdict, and its refusals."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from manieval.errors import ExitCode
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory
from server.kit.settings import Settings
from server.models import Challenge, State, User
from server.submissions.reports import report_final, report_state
from testkit.factories import SUITE, queue_submission, result_doc
from tests.cli.conftest import LiveServer, participant
from tests.web.helpers import WEB_CONDITIONS


@pytest.fixture
def db(live: LiveServer) -> Iterator[Session]:
    """The live server's own database, to store finished submissions in."""
    settings = Settings(dev_mode=True, data_dir=live.data_dir, cookie_secure=False)
    engine = make_engine(settings.resolved_database_url)
    with session_factory(engine)() as session:
        yield session
    engine.dispose()


def submitted(
    db: Session,
    username: str,
    successes: list[bool],
    *,
    phase: str = "dev",
    state: State = State.SUCCEEDED,
    slug: str = "server-tiny",
) -> int:
    """A submission of `username` to `slug` that ended in `state` with these episode
    outcomes, through the worker's reporting path."""
    user = db.scalars(select(User).where(User.username == username)).one()
    challenge = db.scalars(
        select(Challenge).where(Challenge.slug == slug).options(selectinload(Challenge.phases))
    ).one()
    s = queue_submission(db, user, challenge, phase)
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    doc = result_doc(successes, phase=phase, conditions=WEB_CONDITIONS)
    assert report_final(db, s.id, 1, state, "done", result=doc)
    db.commit()
    return s.id


def table_rows(output: str) -> list[list[str]]:
    """The cells of each row of a rich table."""
    return [
        [cell.strip() for cell in line.strip().strip("│").split("│")]
        for line in output.splitlines()
        if line.strip().startswith("│")
    ]


def paired(both: int, only_a: int, only_b: int, neither: int) -> tuple[list[bool], list[bool]]:
    a = [True] * (both + only_a) + [False] * (only_b + neither)
    b = [True] * both + [False] * only_a + [True] * only_b + [False] * neither
    return a, b


def test_compare_prints_the_paired_table_and_a_verdict(
    live: LiveServer, db: Session, tmp_path: Path
) -> None:
    alice = participant(live, tmp_path, "alice")
    # 65 against 50 of 100: the Wilson intervals overlap, but A wins all 15 discordant pairs.
    better, worse = paired(both=50, only_a=15, only_b=0, neither=35)
    a, b = submitted(db, "alice", better), submitted(db, "alice", worse)
    r = alice.run("compare", str(a), str(b))
    assert r.exit_code == 0, r.output
    assert "condition nominal" in r.stdout
    rows = {cells[0]: cells[1:] for cells in table_rows(r.stdout)}
    assert rows["PickCube-v1"] == ["50", "15", "0", "35", "65/100", "50/100", "6.1e-05"]
    assert rows["pooled"] == rows["PickCube-v1"]
    assert f"{a} is better than {b} at 0.05 (p = 6.1e-05, McNemar exact)" in r.stdout

    r = alice.run("compare", str(b), str(a), "--json")
    assert r.exit_code == 0, r.output
    found = json.loads(r.stdout)
    assert (found["condition"], found["significant"], found["p_value"]) == (
        "nominal",
        True,
        2**-14,
    )
    assert found["pooled"] == {
        "both": 50,
        "only_a": 0,
        "only_b": 15,
        "neither": 35,
        "p_value": 2**-14,
    }
    assert [t["env_id"] for t in found["tasks"]] == ["PickCube-v1"]


def test_compare_says_when_the_paired_test_does_not_separate(
    live: LiveServer, db: Session, tmp_path: Path
) -> None:
    carol = participant(live, tmp_path, "carol")
    # 58 against 38 of 100: the intervals are apart, yet B wins 38 of the 96 discordant pairs.
    first, second = paired(both=0, only_a=58, only_b=38, neither=4)
    a, b = submitted(db, "carol", first), submitted(db, "carol", second)
    r = carol.run("compare", str(a), str(b))
    assert r.exit_code == 0, r.output
    assert "no significant difference at 0.05 (p = 0.0519, McNemar exact)" in r.stdout
    assert f"{a} alone solved 58, {b} alone 38 of 100 paired episodes" in r.stdout
    r = carol.run("compare", str(a), str(b), "--alpha", "0.1", "--json")
    assert json.loads(r.stdout)["significant"] is True


def test_compare_refuses_what_it_cannot_pair_or_read(
    live: LiveServer, db: Session, tmp_path: Path
) -> None:
    dave = participant(live, tmp_path / "dave", "dave")
    erin = participant(live, tmp_path / "erin", "erin")
    mine = submitted(db, "dave", [True, False])
    theirs = submitted(db, "erin", [True, True])
    secret_phase = submitted(db, "dave", [True, True], phase="test")
    r = dave.run("compare", str(mine), str(theirs))
    assert r.exit_code == ExitCode.FORBIDDEN, r.output
    assert f"cannot read the episodes of submission {theirs}" in r.stderr
    assert "only their owner (or team) and admins" in r.stderr

    ended = submitted(db, "dave", [False], state=State.FAILED)
    r = dave.run("compare", str(mine), str(ended))
    assert r.exit_code == ExitCode.CONFLICT, r.output
    assert f"submission {ended} ended failed, not succeeded" in r.stderr

    r = erin.run("compare", str(theirs), "999999")
    assert r.exit_code == ExitCode.NOT_FOUND, r.output
    r = dave.run("compare", str(mine), str(secret_phase))
    assert r.exit_code == ExitCode.CONFLICT, r.output
    assert "ran server-tiny/dev and submission" in r.stderr
    assert "ran server-tiny/test" in r.stderr
    r = dave.run("compare", str(mine), str(mine), "--alpha", "1")
    assert r.exit_code == ExitCode.USAGE, r.output


def test_the_board_groups_neighbours_as_compare_explains(
    live: LiveServer, db: Session, tmp_path: Path
) -> None:
    ada = participant(live, tmp_path / "ada", "ada")
    participant(live, tmp_path / "bea", "bea")
    # A board of their own: the module's other tests submit to server-tiny.
    suite = tmp_path / "paired.yaml"
    suite.write_text(SUITE.read_text().replace("name: server-tiny", "name: paired-tiny"))
    load_challenge(db, suite, ChallengeOptions(), seed_secret="s" * 32)
    db.commit()
    # Overlapping intervals (65 and 50 of 100) that the paired test separates: two groups.
    better, worse = paired(both=50, only_a=15, only_b=0, neither=35)
    a = submitted(db, "ada", better, slug="paired-tiny")
    b = submitted(db, "bea", worse, slug="paired-tiny")
    r = ada.run("leaderboard", "paired-tiny")
    assert r.exit_code == 0, r.output
    assert [cells[:3] for cells in table_rows(r.stdout)] == [["1", "G1", "ada"], ["2", "G2", "bea"]]
    r = ada.run("leaderboard", "paired-tiny", "--format", "markdown")
    assert r.exit_code == 0, r.output
    assert "| 1 | 1 | ada | 0.650 [0.553, 0.736] |" in r.stdout
    assert "tie groups: McNemar's exact test, Holm\\-corrected, at 0\\.05" in r.stdout
    r = ada.run("leaderboard", "paired-tiny", "--format", "latex")
    assert r.exit_code == 0, r.output
    assert r"2 & 2 & bea & 0.500 [0.404, 0.596] & 0.500 [0.404, 0.596] \\" in r.stdout
    assert ada.run("leaderboard", "paired-tiny", "--csv", "--format", "latex").exit_code == (
        ExitCode.USAGE
    )

    # An admin may read both submissions' episodes: compare prints the table behind the groups.
    user = db.scalars(select(User).where(User.username == "ada")).one()
    user.is_admin = True
    db.commit()
    r = ada.run("compare", str(a), str(b))
    assert r.exit_code == 0, r.output
    rows = {cells[0]: cells[1:] for cells in table_rows(r.stdout)}
    assert rows["pooled"] == ["50", "15", "0", "35", "65/100", "50/100", "6.1e-05"]
    assert f"{a} is better than {b} at 0.05" in r.stdout
