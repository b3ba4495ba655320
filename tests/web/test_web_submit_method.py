"""The submit form's method fields: kept with the submission, or refused by their fields."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import Challenge, Submission
from testkit.factories import RecordingQueue, make_user
from tests.web.helpers import browser
from tests.web.test_web_submit import field_error, send

PAPER = "https://arxiv.org/abs/2302.04659"


def test_the_method_and_its_links_are_kept_with_the_submission(
    client: TestClient, db: Session, tiny: Challenge, work: RecordingQueue
) -> None:
    make_user(db, "alice")
    r = send(browser(client, "alice"), method="Diffusion Policy", paper_url=PAPER, code_url="")
    assert r.status_code == 303  # type: ignore[attr-defined]
    s = db.scalars(select(Submission)).one()
    assert (s.method, s.paper_url, s.code_url) == ("Diffusion Policy", PAPER, None)


def test_a_link_that_is_no_web_address_is_explained_by_its_field(
    client: TestClient, db: Session, tiny: Challenge, work: RecordingQueue
) -> None:
    make_user(db, "alice")
    r = send(browser(client, "alice"), method="ACT", code_url="javascript:alert(1)")
    assert r.status_code == 200  # type: ignore[attr-defined]
    page = r.text  # type: ignore[attr-defined]
    assert "http" in field_error(page, "code_url")
    assert 'value="ACT"' in page  # what was typed is kept
    assert "javascript:alert(1)" in page  # shown back as text in the field, never as a link
    assert 'href="javascript' not in page
    assert db.scalars(select(Submission)).all() == []
