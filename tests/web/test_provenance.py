"""Provenance where people read results: the submission's page and API say how a result was
produced, and boards mark entries evaluated in another environment than the service's now."""

from __future__ import annotations

import csv
import io

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from evaluator.results import Provenance
from server.models import Challenge, State, Submission
from server.submissions.reports import report_final, report_state
from testkit.factories import make_user, queue_submission, result_doc, tiny_provenance

BOARD = "/api/v1/challenges/server-tiny/leaderboard?phase=dev"


def evaluated(
    db: Session,
    username: str,
    challenge: Challenge,
    successes: list[bool],
    provenance: Provenance | None,
) -> Submission:
    """A succeeded submission whose result records `provenance` (None: none, as before 1.2)."""
    s = queue_submission(db, make_user(db, username), challenge)
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    doc = result_doc(successes, provenance=provenance, recorded=provenance is not None)
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=doc)
    db.commit()
    return s


def test_the_submission_page_and_api_say_how_the_result_was_produced(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    recorded = tiny_provenance()
    s = evaluated(db, "alice", tiny, [True, False], recorded)
    html = client.get(f"/submissions/{s.id}").text
    section = html.split('id="provenance"')[1].split("</section>")[0]
    assert "How this was produced" in section
    env = recorded.environment
    assert f"ManiSkill {env.mani_skill}, SAPIEN {env.sapien}" in section
    assert "physx_cpu simulation, sapien_cpu rendering" in section
    assert f"sha256 {env.suite_sha256[:12]}" in section
    assert "PickCube-v1: pd_ee_delta_pose, at most 12 steps" in section
    assert "ends an episode at its first success" in section
    assert 'ManiEval 0.1.0, commit <code class="hash">' + "f" * 12 + "</code>" in section
    assert "x@sha256:" + "0" * 64 in section  # the policy's pinned image
    assert "AMD EPYC 7B13" in section

    body = client.get(f"/api/v1/submissions/{s.id}").json()
    assert Provenance.model_validate(body["provenance"]) == recorded


def test_a_result_recorded_before_provenance_shows_none_and_the_api_says_null(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    s = evaluated(db, "alice", tiny, [True], None)
    assert 'id="provenance"' not in client.get(f"/submissions/{s.id}").text
    assert client.get(f"/api/v1/submissions/{s.id}").json()["provenance"] is None


def test_a_board_marks_entries_evaluated_in_another_environment_with_what_differs(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    evaluated(db, "alice", tiny, [True] * 4, tiny_provenance())
    evaluated(db, "bobby", tiny, [True] * 3 + [False], tiny_provenance(mani_skill="3.0.0"))
    evaluated(db, "carol", tiny, [True] * 2 + [False] * 2, tiny_provenance(suite_sha256="e" * 64))
    evaluated(db, "dave", tiny, [False] * 4, None)  # versions "0": ManiSkill, SAPIEN, torch

    items = client.get(BOARD).json()["items"]
    assert [(r["username"], r["environment_differs"]) for r in items] == [
        ("alice", []),
        ("bobby", ["mani_skill"]),
        ("carol", ["suite_sha256"]),
        ("dave", ["mani_skill", "sapien", "torch"]),
    ]

    header, *rows = csv.reader(io.StringIO(client.get(BOARD + "&format=csv").text))
    assert header[-1] == "environment_differs"
    assert [(r[1], r[-1]) for r in rows] == [
        ("alice", ""),
        ("bobby", "mani_skill"),
        ("carol", "suite_sha256"),
        ("dave", "mani_skill;sapien;torch"),
    ]

    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert html.count('class="badge badge-env"') == 3 + 1  # the marked rows and the legend's
    assert ">other ManiSkill</span>" in html
    assert ">other suite</span>" in html
    assert ">other ManiSkill, SAPIEN, torch</span>" in html


def test_a_board_with_every_entry_in_the_current_environment_shows_no_mark(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    evaluated(db, "alice", tiny, [True, False], tiny_provenance())
    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert "badge-env" not in html
    assert client.get(BOARD).json()["items"][0]["environment_differs"] == []
