"""An organizer's bulk tools: re-running the stuck evaluations, exporting a challenge's
submissions with their results."""

from __future__ import annotations

import csv
import io
from datetime import timedelta

from fastapi.testclient import TestClient
from sqlalchemy import update
from sqlalchemy.orm import Session

from server import audit
from server.models import Challenge, State, Submission, User, utcnow
from server.submissions.reports import report_state
from testkit.factories import RecordingQueue, queue_submission
from tests.server.organizers import (  # noqa: F401 - pytest fixtures
    API,
    fixture_people,
    fixture_tiny,
    fixture_tokens,
)
from tests.web.helpers import finished

EXPORT = f"{API}/admin/challenges/server-tiny/export"


def running(db: Session, user: User, challenge: Challenge, **values: object) -> Submission:
    """A submission running attempt 1, then given `values` (an old heartbeat, a deadline)."""
    s = queue_submission(db, user, challenge)
    db.flush()
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    if values:
        db.execute(update(Submission).where(Submission.id == s.id).values(**values))
    db.commit()
    return s


def where(db: Session, submission_id: int) -> tuple[State, int]:
    found = db.get(Submission, submission_id)
    assert found is not None
    return found.state, found.attempt


def test_rerun_stuck_queues_the_silent_and_the_late_again_and_leaves_the_others(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
    work: RecordingQueue,
) -> None:
    long_ago = utcnow() - timedelta(hours=1)
    silent = running(db, people["alice"], tiny, heartbeat_at=long_ago)
    late = running(db, people["bob"], tiny, deadline_at=long_ago)
    fine = running(db, people["alice"], tiny)
    done = finished(db, people["bob"], tiny, [True, False])

    path = f"{API}/admin/rerun-stuck"
    assert client.post(path, json={}, headers=tokens["alice"]).status_code == 403
    assert client.post(path, json={"challenge": "nope"}, headers=tokens["judge"]).status_code == 404
    r = client.post(
        path, json={"challenge": "server-tiny", "reason": "node lost"}, headers=tokens["judge"]
    )
    assert r.status_code == 200, r.text
    assert r.json()["requeued"] == sorted([silent.id, late.id])
    db.expire_all()
    assert {s.id: where(db, s.id) for s in (silent, late, fine, done)} == {
        silent.id: (State.QUEUED, 2),
        late.id: (State.QUEUED, 2),
        fine.id: (State.RUNNING, 1),
        done.id: (State.SUCCEEDED, 1),
    }
    assert {(silent.id, 2), (late.id, 2)} <= set(work.sent)
    (record,) = audit.records(db, action="challenge.rerun_stuck")
    assert (record.actor, record.reason, record.target_id) == ("judge", "node lost", tiny.id)
    assert record.detail == {"submissions": sorted([silent.id, late.id])}
    # Nothing stuck now: nothing done, nothing recorded.
    again = client.post(path, json={}, headers=tokens["judge"])
    assert again.json()["requeued"] == []
    assert len(audit.records(db, action="challenge.rerun_stuck")) == 1


def test_the_export_has_one_row_per_submission_as_csv_and_json(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    tokens: dict[str, dict[str, str]],
) -> None:
    best = finished(db, people["alice"], tiny, [True, True])
    failed = finished(db, people["bob"], tiny, [False], state=State.FAILED, reason="it crashed")
    queued = queue_submission(db, people["bob"], tiny)
    db.commit()
    judge = tokens["judge"]
    assert (
        client.post(
            f"{API}/submissions/{best.id}/disqualify", json={"reason": "=cheat"}, headers=judge
        ).status_code
        == 200
    )

    r = client.get(EXPORT, headers=judge)
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/csv")
    assert 'filename="server-tiny-submissions.csv"' in r.headers["content-disposition"]
    found = list(csv.DictReader(io.StringIO(r.text)))
    assert [int(row["submission_id"]) for row in found] == [best.id, failed.id, queued.id]
    first, second, third = found
    assert (first["username"], first["phase"], first["state"], first["score"]) == (
        "alice",
        "dev",
        "succeeded",
        "1.0000",
    )
    assert (first["condition nominal"], first["condition obs_noise"]) == ("1.0000", "1.0000")
    assert (first["disqualified"], first["moderation_reason"]) == ("True", "'=cheat")  # defused
    assert first["pinned_image"].startswith("x@sha256:")
    assert first["finished_at"]
    assert first["created_at"]
    assert (second["state"], second["reason"], second["score"]) == ("failed", "it crashed", "")
    assert (third["state"], third["attempt"], third["finished_at"]) == ("queued", "1", "")

    as_json = client.get(EXPORT + "?format=json", headers=judge)
    assert as_json.headers["content-type"].startswith("application/json")
    items = as_json.json()
    assert [i["submission_id"] for i in items] == [best.id, failed.id, queued.id]
    assert items[0]["moderation_reason"] == "=cheat"  # JSON as it is
    assert items[0]["condition nominal"] == 1.0
    assert items[1]["score"] is None
    assert client.get(EXPORT + "?phase=test&format=json", headers=judge).json() == []
    dev = client.get(EXPORT + "?phase=dev", headers=judge)
    assert 'filename="server-tiny-dev-submissions.csv"' in dev.headers["content-disposition"]

    assert client.get(EXPORT, headers=tokens["alice"]).status_code == 403
    assert client.get(f"{API}/admin/challenges/nope/export", headers=judge).status_code == 404
    assert client.get(EXPORT + "?format=xml", headers=judge).status_code == 422
    assert client.get(EXPORT + "?phase=nope", headers=judge).status_code == 422
