"""The submit form with the server's errors by their fields, and the lists of submissions."""

from __future__ import annotations

import re
from datetime import UTC, datetime, timedelta

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import Challenge, State, Submission
from testkit.factories import RecordingQueue, make_challenge, make_user
from tests.web.helpers import browser, csrf_of, finished

FORM = "/challenges/server-tiny/submit"
IMAGE = "127.0.0.1:5000/team/policy:v1"


def send(client: TestClient, **fields: str) -> object:
    form = {"phase": "dev", "image": IMAGE, "description": "", "visibility": "public"}
    form.update(fields)
    return client.post(FORM, data={"csrf_token": csrf_of(client.get(FORM).text), **form})


def field_error(html: str, field: str) -> str:
    found = re.search(rf'<p class="field-error" id="{field}-error">([^<]*)</p>', html)
    assert found, f"no error next to {field}"
    return found.group(1)


def test_a_valid_submission_is_pinned_queued_and_shown(
    client: TestClient, db: Session, tiny: Challenge, work: RecordingQueue
) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    r = send(alice, description="first try", visibility="private")
    assert r.status_code == 303  # type: ignore[attr-defined]
    sid = int(r.headers["location"].rsplit("/", 1)[1])  # type: ignore[attr-defined]
    s = db.scalars(select(Submission).where(Submission.id == sid)).one()
    assert s.pinned_image.startswith("127.0.0.1:5000/team/policy@sha256:")
    assert not s.public
    assert s.description == "first try"
    assert work.sent == [(sid, 1)]
    page = alice.get(f"/submissions/{sid}").text
    assert "queued" in page
    assert "first try" in page


@pytest.mark.parametrize(
    ("image", "words"),
    [
        ("", "Enter an image reference."),
        ("Team/Policy:v1", "lowercase"),
        ("127.0.0.1:5000/team/policy@sha256:abc", "64 lowercase hex"),
        ("local:nope", "one of: "),
        ("x" * 600, "At most 512"),
    ],
)
def test_a_bad_image_reference_is_explained_next_to_the_image_field(
    client: TestClient, db: Session, tiny: Challenge, image: str, words: str
) -> None:
    make_user(db, "alice")
    alice = browser(client, "alice")
    r = send(alice, image=image, description="keep me")
    assert r.status_code == 200  # type: ignore[attr-defined]  # the form again
    html = r.text  # type: ignore[attr-defined]
    assert words in field_error(html, "image") or words in html
    assert re.search(r'id="image"[^>]*aria-invalid="true"', html)
    assert ">keep me</textarea>" in html  # what was typed is kept
    assert alice.get("/submissions").text.count('href="/submissions/') == 0


def test_a_closed_or_unknown_phase_is_explained_next_to_the_phase_field(
    client: TestClient, db: Session
) -> None:
    past = datetime.now(UTC) - timedelta(days=1)
    make_challenge(db, closes={"dev": past}, opens={"dev": past - timedelta(days=9)})
    make_user(db, "alice")
    alice = browser(client, "alice")
    closed = send(alice)
    assert closed.status_code == 200  # type: ignore[attr-defined]  # the form again
    assert "closed" in field_error(closed.text, "phase")  # type: ignore[attr-defined]
    unknown = send(alice, phase="final")
    assert unknown.status_code == 200  # type: ignore[attr-defined]  # the form again
    assert "one of: dev, test" in field_error(unknown.text, "phase")  # type: ignore[attr-defined]


def test_quota_exceeded_says_when_it_resets(client: TestClient, db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=1, quota_concurrent=1)
    alice_user = make_user(db, "alice")
    s = finished(db, alice_user, challenge, [True])
    alice = browser(client, "alice")
    r = send(alice)
    assert r.status_code == 200  # type: ignore[attr-defined]  # the form again
    html = r.text  # type: ignore[attr-defined]
    assert 'role="alert"' in html
    assert "daily quota of 1" in html
    resets = s.created_at + timedelta(days=1)
    assert f'<time datetime="{resets.isoformat()}">' in html
    assert int(r.headers["retry-after"]) > 0  # type: ignore[attr-defined]


def test_my_submissions_lists_only_mine_and_the_admin_list_is_for_admins(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    alice_user, bob_user = make_user(db, "alice"), make_user(db, "bob")
    make_user(db, "judge", admin=True)
    mine = finished(db, alice_user, tiny, [True])
    theirs = finished(db, bob_user, tiny, [False], state=State.FAILED, reason="crashed")
    listed = browser(client, "alice").get("/submissions").text
    assert f'href="/submissions/{mine.id}"' in listed
    assert f'href="/submissions/{theirs.id}"' not in listed
    assert browser(client, "alice").get("/admin/submissions").status_code == 403
    judge = browser(client, "judge")
    everything = judge.get("/admin/submissions").text
    assert f"/submissions/{mine.id}" in everything
    assert f"/submissions/{theirs.id}" in everything
    failed_only = judge.get("/admin/submissions?state=failed").text
    assert f"/submissions/{theirs.id}" in failed_only
    assert f'/submissions/{mine.id}"' not in failed_only
