"""An organizer's moderation: hiding and disqualifying with a reason, on the board and the
submission's page, through the API and the web forms; each action's audit record."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server import audit
from server.models import Challenge, State, Submission, User
from server.submissions.reports import report_final, report_state
from testkit.factories import result_doc
from tests.server.organizers import (  # noqa: F401 - pytest fixtures
    API,
    fixture_people,
    fixture_tiny,
    fixture_tokens,
)
from tests.web.helpers import WEB_CONDITIONS, browser, csrf_of, finished

BOARD = f"{API}/challenges/server-tiny/leaderboard?phase=dev"
WHY = "the policy reads the seed from the environment"


def rows(client: TestClient) -> list[tuple[int | None, str, int, str | None]]:
    items = client.get(BOARD).json()["items"]
    return [(r["rank"], r["username"], r["submission_id"], r["disqualified"]) for r in items]


def test_moderation_needs_an_admin_a_reason_and_a_submission(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    s = finished(db, people["alice"], tiny, [True, False])
    for action in ("hide", "disqualify"):
        url = f"{API}/submissions/{s.id}/{action}"
        assert client.post(url, json={"reason": WHY}, headers=tokens["alice"]).status_code == 403
        assert client.post(url, json={"reason": WHY}).status_code == 401
        for body in ({}, {"reason": "  "}, {"reason": "x" * 2001}):
            r = client.post(url, json=body, headers=tokens["judge"])
            assert r.status_code == 422, body
            assert "reason" in r.json()["error"]["fields"]
        missing = f"{API}/submissions/999999/{action}"
        assert (
            client.post(missing, json={"reason": WHY}, headers=tokens["judge"]).status_code == 404
        )
    for action in ("unhide", "reinstate"):  # nothing to undo
        r = client.post(f"{API}/submissions/{s.id}/{action}", json={}, headers=tokens["judge"])
        assert r.status_code == 409
    # nothing was done, nothing recorded (but the challenge's load, from the command line)
    assert [record.action for record in audit.records(db)] == ["challenge.load"]


def test_a_disqualified_row_stays_on_the_board_unranked_after_the_ranked_rows(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    best = finished(db, people["alice"], tiny, [True, True])
    weaker = finished(db, people["alice"], tiny, [False, False])
    bob = finished(db, people["bob"], tiny, [True, False])
    assert rows(client) == [(1, "alice", best.id, None), (2, "bob", bob.id, None)]

    r = client.post(
        f"{API}/submissions/{best.id}/disqualify", json={"reason": WHY}, headers=tokens["judge"]
    )
    assert r.status_code == 200, r.text
    assert (r.json()["disqualified"], r.json()["moderation_reason"]) == (True, WHY)
    # Her next submission is her ranked row; the disqualified one follows the ranked rows.
    assert rows(client) == [
        (1, "bob", bob.id, None),
        (2, "alice", weaker.id, None),
        (None, "alice", best.id, WHY),
    ]
    csv_lines = client.get(BOARD + "&format=csv").text.splitlines()
    assert "disqualified" in csv_lines[0].split(",")
    assert csv_lines[3].startswith(",alice,False,1.0000")
    assert WHY in csv_lines[3]
    page = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert '<span class="badge badge-disqualified">disqualified</span>' in page
    assert f"Disqualified by the organizers: {WHY}" in page
    shown = browser(client).get(f"/submissions/{best.id}").text  # anyone: it is on the board
    assert "Disqualified by the organizers" in shown
    assert WHY in shown
    markdown = client.get(BOARD + "&format=markdown").text
    assert "alice (disqualified)" in markdown

    r = client.post(f"{API}/submissions/{best.id}/reinstate", json={}, headers=tokens["judge"])
    assert r.status_code == 200
    assert (r.json()["disqualified"], r.json()["moderation_reason"]) == (False, None)
    assert rows(client) == [(1, "alice", best.id, None), (2, "bob", bob.id, None)]


def test_a_hidden_submission_leaves_every_board_and_its_owner_is_told_why(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    s = finished(db, people["alice"], tiny, [True, True])
    bob = finished(db, people["bob"], tiny, [True, False])
    r = client.post(f"{API}/submissions/{s.id}/hide", json={"reason": WHY}, headers=tokens["judge"])
    assert r.status_code == 200
    assert rows(client) == [(1, "bob", bob.id, None)]
    alice = browser(client, "alice")
    page = alice.get(f"/submissions/{s.id}").text
    assert "Hidden by the organizers" in page
    assert WHY in page
    assert browser(client, "bob").get(f"/submissions/{s.id}").status_code == 404
    detail = client.get(f"{API}/submissions/{s.id}", headers=tokens["alice"]).json()
    assert (detail["hidden"], detail["moderation_reason"]) == (True, WHY)

    r = client.post(
        f"{API}/submissions/{s.id}/unhide",
        json={"reason": "appeal upheld"},
        headers=tokens["judge"],
    )
    assert r.status_code == 200
    assert rows(client) == [(1, "alice", s.id, None), (2, "bob", bob.id, None)]
    assert "Hidden by the organizers" not in alice.get(f"/submissions/{s.id}").text


def test_the_submission_page_moderates_with_a_reason_a_confirmation_and_its_form_token(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, User]
) -> None:
    s = finished(db, people["alice"], tiny, [True, False])
    judge = browser(client, "judge")
    page = judge.get(f"/submissions/{s.id}").text
    assert f'action="/submissions/{s.id}/disqualified"' in page
    assert f'data-confirm="Disqualify submission #{s.id}?"' in page
    assert 'name="reason" maxlength="2000" required' in page
    assert "Disqualify" not in browser(client, "alice").get(f"/submissions/{s.id}").text
    token = csrf_of(page)
    url = f"/submissions/{s.id}/disqualified"
    no_token = judge.post(url, data={"disqualified": "true", "reason": WHY})
    assert no_token.status_code == 403
    said = judge.post(url, data={"csrf_token": token, "disqualified": "true"})
    assert said.status_code == 422  # say why
    owner = browser(client, "alice")
    owned = csrf_of(owner.get(f"/submissions/{s.id}").text)
    mine = owner.post(url, data={"csrf_token": owned, "disqualified": "true", "reason": WHY})
    assert mine.status_code == 403
    done = judge.post(url, data={"csrf_token": token, "disqualified": "true", "reason": WHY})
    assert done.status_code == 303
    db.refresh(s)
    assert (s.disqualified, s.moderation_reason) == (True, WHY)
    back = judge.post(url, data={"csrf_token": token, "disqualified": "false", "reason": ""})
    assert back.status_code == 303
    db.refresh(s)
    assert (s.disqualified, s.moderation_reason) == (False, None)
    records = audit.records(db, target_kind="submission", target_id=s.id)
    assert [(r.action, r.actor, r.reason) for r in records] == [
        ("submission.reinstate", "judge", ""),
        ("submission.disqualify", "judge", WHY),
    ]


def test_each_organizer_action_writes_its_audit_record(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    judge = tokens["judge"]
    s = finished(db, people["alice"], tiny, [True, False])
    calls = [
        (f"/submissions/{s.id}/hide", {"reason": WHY}),
        (f"/submissions/{s.id}/unhide", {}),
        (f"/submissions/{s.id}/rerun", {"reason": "a flaky node"}),
    ]
    for path, body in calls:
        assert client.post(API + path, json=body, headers=judge).status_code == 200, path
    patched = client.patch(f"{API}/submissions/{s.id}", json={"baseline": True}, headers=judge)
    assert patched.status_code == 200
    bob = finished(db, people["bob"], tiny, [True, True])
    r = client.post(f"{API}/challenges/server-tiny/phases/dev/reevaluate", headers=judge)
    assert r.status_code == 200, r.text
    assert r.json()["board_version"] == 2
    assert r.json()["submissions"]  # bob's entry, copied
    again = client.post(f"{API}/challenges/server-tiny/phases/dev/reevaluate", headers=judge)
    assert again.status_code == 409
    closed = client.post(f"{API}/challenges/server-tiny/phases/dev/close", headers=judge)
    assert closed.status_code == 200

    page = client.get(f"{API}/admin/audit", headers=judge).json()
    assert [(r["action"], r["actor"], r["challenge"]) for r in page["items"]] == [
        ("phase.close", "judge", "server-tiny"),
        ("phase.reevaluate", "judge", "server-tiny"),
        ("submission.baseline", "judge", "server-tiny"),
        ("submission.rerun", "judge", "server-tiny"),
        ("submission.unhide", "judge", "server-tiny"),
        ("submission.hide", "judge", "server-tiny"),
        ("challenge.load", audit.command_line_actor(), "server-tiny"),
    ]
    assert page["next_before_id"] is None
    reevaluated = page["items"][1]
    assert reevaluated["detail"]["board_version"] == 2
    assert reevaluated["detail"]["submissions"] == r.json()["submissions"]
    assert page["items"][3]["reason"] == "a flaky node"
    assert page["items"][5]["reason"] == WHY
    assert bob.id not in reevaluated["detail"]["submissions"]  # copies, not the originals

    first = client.get(f"{API}/admin/audit?limit=4", headers=judge).json()
    rest = client.get(
        f"{API}/admin/audit?before_id={first['next_before_id']}", headers=judge
    ).json()
    assert [r["id"] for r in first["items"] + rest["items"]] == [r["id"] for r in page["items"]]
    only = client.get(f"{API}/admin/audit?action=phase.close", headers=judge).json()
    assert [r["action"] for r in only["items"]] == ["phase.close"]
    mine = client.get(f"{API}/admin/audit?challenge=server-tiny", headers=judge).json()
    assert len(mine["items"]) == 7
    assert client.get(f"{API}/admin/audit?challenge=nope", headers=judge).status_code == 404
    assert client.get(f"{API}/admin/audit", headers=tokens["alice"]).status_code == 403


def test_reevaluating_over_the_api_is_for_admins_and_known_phases(
    client: TestClient, tiny: Challenge, tokens: dict[str, dict[str, str]]
) -> None:
    path = f"{API}/challenges/server-tiny/phases/dev/reevaluate"
    assert client.post(path, headers=tokens["alice"]).status_code == 403
    missing = f"{API}/challenges/server-tiny/phases/nope/reevaluate"
    assert client.post(missing, headers=tokens["judge"]).status_code == 404
    assert client.post(path, headers=tokens["judge"]).status_code == 409  # no entries


def test_attempts_are_shown_side_by_side_to_the_owner_and_admins(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    s = finished(db, people["alice"], tiny, [True, False])
    r = client.post(f"{API}/submissions/{s.id}/rerun", headers=tokens["judge"])
    assert r.status_code == 200
    assert report_state(db, s.id, 2, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 2, State.RUNNING, "evaluating")
    doc = result_doc([True, True], conditions=WEB_CONDITIONS)
    assert report_final(db, s.id, 2, State.SUCCEEDED, "second run done", result=doc)
    db.commit()
    for who in ("alice", "judge"):
        page = browser(client, who).get(f"/submissions/{s.id}").text
        assert "Attempts side by side" in page
        table = page[page.index('id="attempts"') :]
        assert "Attempt 1" in table
        assert "Attempt 2" in table
        assert "done" in table
        assert "second run done" in table
        assert "1 / 2" in table
        assert "2 / 2" in table
    assert "Attempts side by side" not in browser(client, "bob").get(f"/submissions/{s.id}").text
    once = finished(db, people["bob"], tiny, [True, True])
    assert "Attempts side by side" not in browser(client, "bob").get(f"/submissions/{once.id}").text


def test_a_submission_hidden_through_patch_needs_a_reason_too(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    s = finished(db, people["alice"], tiny, [True, False])
    url = f"{API}/submissions/{s.id}"
    assert client.patch(url, json={"hidden": True}, headers=tokens["judge"]).status_code == 422
    db.expire_all()
    assert db.get(Submission, s.id).hidden is False  # type: ignore[union-attr]
    ok = client.patch(url, json={"hidden": True, "reason": WHY}, headers=tokens["judge"])
    assert ok.status_code == 200
    assert ok.json()["moderation_reason"] == WHY
