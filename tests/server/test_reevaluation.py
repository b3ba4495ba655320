"""Re-evaluation (docs/server.md): every entry of a board run again into a new board version,
charged to nobody's quota, published once every re-run has ended; the previous version stays
readable. Runs end here through the workers' reporting path (the real evaluation end to end is
test_reevaluation_embedded.py)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from evaluator.results import SuiteRef
from server.challenges.quota import quota_use
from server.kit.errors import Conflict, Forbidden
from server.models import Challenge, Phase, State, Submission, User, utcnow
from server.submissions.moderation import moderate, rerun
from server.submissions.reevaluation import (
    NothingToReevaluate,
    Started,
    reevaluate,
)
from server.submissions.reports import report_final, report_state
from testkit.factories import (
    RecordingQueue,
    make_challenge,
    make_user,
    queue_submission,
    result_doc,
)
from tests.web.helpers import WEB_CONDITIONS, browser, csrf_of, finished

API = "/api/v1/challenges/server-tiny/leaderboard"
NEW_SUITE = SuiteRef(name="server-tiny", version=2, sha256="ab" * 32)


@pytest.fixture
def strict(db: Session) -> Challenge:
    """server-tiny with one submission a day and one at a time: any re-run that counted
    against a participant would use their quota up."""
    return make_challenge(db, quota_per_day=1, quota_concurrent=1)


@pytest.fixture
def people(db: Session) -> dict[str, User]:
    return {name: make_user(db, name) for name in ("alice", "bob")} | {
        "judge": make_user(db, "judge", admin=True)
    }


def dev(db: Session, challenge: Challenge) -> Phase:
    """The challenge's dev phase as the database has it now."""
    phase = db.scalar(
        select(Phase)
        .where(Phase.challenge_id == challenge.id, Phase.name == "dev")
        .execution_options(populate_existing=True)
    )
    assert phase is not None
    return phase


def board(client: TestClient, **params: object) -> list[int]:
    r = client.get(API, params={"phase": "dev", **params})
    assert r.status_code == 200, r.text
    return [row["submission_id"] for row in r.json()["items"]]


def end(db: Session, sid: int, state: State, successes: list[bool] | None = None) -> None:
    """A re-evaluation run to `state` through the workers' reporting path, its result (when
    `successes` are given) evaluated on the new suite."""
    assert report_state(db, sid, 1, State.LAUNCHING, "starting")
    assert report_state(db, sid, 1, State.RUNNING, "evaluating")
    result = None
    if successes is not None:
        doc = result_doc(successes, conditions=WEB_CONDITIONS)
        result = doc.model_copy(update={"suite": NEW_SUITE})
    assert report_final(db, sid, 1, state, f"ended {state.value}", result=result)
    db.commit()


def entries(db: Session, strict: Challenge, people: dict[str, User]) -> tuple[int, int]:
    """alice's (1 of 2 episodes) and bob's (2 of 2) succeeded submissions: the board."""
    alice = finished(db, people["alice"], strict, [True, False])
    bob = finished(db, people["bob"], strict, [True, True])
    return alice.id, bob.id


def started(db: Session, challenge: Challenge) -> Started:
    done = reevaluate(db, by=None, challenge=challenge, phase=dev(db, challenge))
    db.commit()
    return done


def test_a_reevaluation_charges_nobody_and_the_board_moves_only_when_every_rerun_ended(
    client: TestClient, db: Session, strict: Challenge, people: dict[str, User]
) -> None:
    alice, bob = entries(db, strict, people)
    now = utcnow()
    quotas = {n: quota_use(db, user=people[n], challenge=strict, now=now) for n in ("alice", "bob")}
    done = started(db, strict)
    assert done.board_version == 2
    copy_of = {
        s.reevaluation_of: s
        for s in db.scalars(select(Submission).where(Submission.id.in_(done.submissions)))
    }
    assert set(copy_of) == {alice, bob}
    assert all(s.state == State.QUEUED and s.board_version == 2 for s in copy_of.values())
    for name in ("alice", "bob"):  # queued re-runs hold nothing: not the day's, not a slot
        assert quota_use(db, user=people[name], challenge=strict, now=now) == quotas[name]
    assert board(client) == [bob, alice]
    assert client.get(API, params={"phase": "dev", "version": 2}).status_code == 404

    end(db, copy_of[alice].id, State.SUCCEEDED, [True, True])
    assert board(client) == [bob, alice]  # one re-run ended: the board stays version 1
    assert dev(db, strict).board_version == 1
    end(db, copy_of[bob].id, State.FAILED)  # the policy's doing on the new suite
    assert dev(db, strict).board_version == 2
    assert board(client) == [copy_of[alice].id]
    assert board(client, version=2) == [copy_of[alice].id]
    assert board(client, version=1) == [bob, alice]  # the previous board, as it was
    csv = client.get(API, params={"phase": "dev", "version": 1, "format": "csv"}).text
    assert f",{bob}," in csv
    assert client.get(API, params={"phase": "dev", "version": 3}).status_code == 404
    for name in ("alice", "bob"):
        assert quota_use(db, user=people[name], challenge=strict, now=now) == quotas[name]


def test_a_submission_made_during_a_reevaluation_counts_for_the_new_version(
    client: TestClient, db: Session, strict: Challenge, people: dict[str, User]
) -> None:
    alice, bob = entries(db, strict, people)
    done = started(db, strict)
    carol = make_user(db, "carol")
    new = queue_submission(db, carol, strict)  # runs on the new suite: not on version 1
    db.commit()
    assert new.board_version == 2
    end(db, new.id, State.SUCCEEDED, [True, True])
    assert board(client) == [bob, alice]
    for sid in done.submissions:
        end(db, sid, State.SUCCEEDED, [False, False])
    assert board(client)[0] == new.id
    assert new.id not in board(client, version=1)


def test_a_rerun_that_ends_in_the_services_error_holds_the_new_version_until_an_admin_acts(
    client: TestClient, db: Session, strict: Challenge, people: dict[str, User]
) -> None:
    entries(db, strict, people)
    done = started(db, strict)
    first, second = (db.get(Submission, sid) for sid in done.submissions)
    assert first is not None
    assert second is not None
    end(db, first.id, State.ERROR)
    end(db, second.id, State.SUCCEEDED, [True, True])
    assert dev(db, strict).board_version == 1  # nobody loses their row to an outage
    rerun(db, admin=people["judge"], submission=first)  # the admin runs it again
    db.commit()
    assert first.attempt == 2
    assert report_state(db, first.id, 2, State.LAUNCHING, "starting")
    assert report_final(db, first.id, 2, State.ERROR, "the cluster again")
    db.commit()
    assert dev(db, strict).board_version == 1
    gives_up = "the cluster fails it every time"  # the admin gives up on it
    moderate(db, by=people["judge"], submission=first, action="hide", reason=gives_up)
    db.commit()
    assert dev(db, strict).board_version == 2
    assert board(client) == [second.id]


def test_a_reevaluation_is_refused_while_one_runs_and_for_an_empty_board(
    db: Session, strict: Challenge, people: dict[str, User]
) -> None:
    with pytest.raises(NothingToReevaluate, match="no entries"):
        reevaluate(db, by=None, challenge=strict, phase=dev(db, strict))
    entries(db, strict, people)
    started(db, strict)
    with pytest.raises(Conflict, match="into board version 2"):
        reevaluate(db, by=None, challenge=strict, phase=dev(db, strict))
    with pytest.raises(Forbidden):
        reevaluate(db, by=people["alice"], challenge=strict, phase=dev(db, strict))


def reevaluate_by_form(client: TestClient, phase: str = "dev") -> int:
    page = client.get("/challenges/server-tiny/leaderboard", params={"phase": phase}).text
    token = csrf_of(page) if "csrf_token" in page else ""
    return client.post(
        "/challenges/server-tiny/reevaluate", data={"csrf_token": token, "phase": phase}
    ).status_code


def test_only_admins_reevaluate_from_the_board_page_and_it_is_recorded_who_did(
    client: TestClient,
    db: Session,
    strict: Challenge,
    people: dict[str, User],
    work: RecordingQueue,
) -> None:
    entries(db, strict, people)
    alice, judge = browser(client, "alice"), browser(client, "judge")
    assert "Re-evaluate phase dev" not in alice.get("/challenges/server-tiny/leaderboard").text
    assert reevaluate_by_form(alice) == 403
    assert reevaluate_by_form(browser(client)) in (401, 403)
    page = judge.get("/challenges/server-tiny/leaderboard", params={"phase": "dev"}).text
    assert "Re-evaluate phase dev" in page
    assert 'data-confirm="Re-evaluate every entry of phase dev into board version 2?"' in page
    no_token = judge.post("/challenges/server-tiny/reevaluate", data={"phase": "dev"})
    assert no_token.status_code == 403
    assert dev(db, strict).pending_board_version is None
    before = len(work.sent)
    assert reevaluate_by_form(judge) == 303
    assert dev(db, strict).pending_board_version == 2
    copies = db.scalars(select(Submission).where(Submission.reevaluation_of.is_not(None))).all()
    assert {(s.id, 1) for s in copies} <= set(work.sent[before:])  # dispatched at once
    r = judge.get(f"/api/v1/submissions/{copies[0].id}")
    assert "re-evaluation of submission" in r.json()["transitions"][0]["reason"]
    assert "by admin judge" in r.json()["transitions"][0]["reason"]
    page = client.get("/challenges/server-tiny/leaderboard", params={"phase": "dev"}).text
    assert "A re-evaluation into version 2 is in progress" in page
    assert "Re-evaluate phase dev" not in judge.get("/challenges/server-tiny/leaderboard").text
    assert reevaluate_by_form(judge) == 409


def test_the_web_board_serves_each_version_and_the_submission_page_shows_both_results(
    client: TestClient, db: Session, strict: Challenge, people: dict[str, User]
) -> None:
    alice, bob = entries(db, strict, people)
    done = started(db, strict)
    for sid in done.submissions:
        end(db, sid, State.SUCCEEDED, [True, True])
    copy = db.scalar(select(Submission).where(Submission.reevaluation_of == alice))
    assert copy is not None
    current = client.get("/challenges/server-tiny/leaderboard", params={"phase": "dev"}).text
    assert "Board version 2 (the current one)" in current
    assert f"/submissions/{copy.id}" in current
    assert f'/submissions/{alice}"' not in current
    old = client.get("/challenges/server-tiny/leaderboard", params={"phase": "dev", "version": 1})
    assert old.status_code == 200
    assert "Board version 1, an earlier evaluation" in old.text
    assert f'/submissions/{alice}"' in old.text
    assert f"/submissions/{copy.id}" not in old.text
    assert "version=1" in old.text  # its downloads and sorts stay on version 1
    missing = client.get("/challenges/server-tiny/leaderboard", params={"version": 9})
    assert missing.status_code == 404
    for shown in (alice, copy.id):  # each page shows both evaluations, each with its suite
        page = client.get(f"/submissions/{shown}").text
        assert "Evaluations on each board version" in page
        assert f'href="/submissions/{copy.id if shown == alice else alice}"' in page
        assert "sha256 " + "ab" * 6 in page  # the re-evaluation's suite
        assert "version 2, " in page
        assert "version 1, " in page
        assert "ManiSkill" in page
    assert "an organizer's re-evaluation of" in client.get(f"/submissions/{copy.id}").text
    lone = finished(db, make_user(db, "carol"), strict, [True, True])
    assert "Evaluations on each board version" not in client.get(f"/submissions/{lone.id}").text
    assert bob in board(client, version=1)
