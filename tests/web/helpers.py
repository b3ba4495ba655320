"""Helpers of the web tests: a logged-in browser-like client per user, forms with their CSRF
token, and submissions run to a final state through the worker's reporting path."""

from __future__ import annotations

import re

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from evaluator.results import Abort, Video
from server.models import Challenge, State, Submission, User
from server.submissions.reports import report_final, report_state
from testkit.factories import PASSWORD, queue_submission, result_doc

WEB_CONDITIONS = ("nominal", "obs_noise")  # the server-tiny suite's conditions

CSRF = re.compile(r'name="csrf_token" value="([^"]*)"')


def csrf_of(html: str) -> str:
    """The CSRF token the page's forms carry."""
    found = CSRF.search(html)
    assert found, "the page has no form with a CSRF token"
    return found.group(1)


def browser(client: TestClient, username: str | None = None) -> TestClient:
    """A separate cookie jar on the same app, logged in through the login form if named."""
    other = TestClient(client.app, base_url="http://testserver", follow_redirects=False)
    if username is not None:
        token = csrf_of(other.get("/login").text)
        r = other.post(
            "/login", data={"login": username, "password": PASSWORD, "csrf_token": token}
        )
        assert r.status_code == 303, r.text
    return other


def finished(
    db: Session,
    user: User,
    challenge: Challenge,
    successes: list[bool],
    *,
    state: State = State.SUCCEEDED,
    reason: str = "done",
    log_tail: str = "",
    public: bool = True,
    description: str = "",
    videos: list[Video] | None = None,
    planned: int | None = None,
    abort: Abort | None = None,
) -> Submission:
    """A submission run to `state` through the worker's reporting path; with `planned`, it
    ended part-way and reports what ran (the `successes`) and the rest not run."""
    s = queue_submission(db, user, challenge)
    s.public = public
    s.description = description
    db.flush()
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    doc = result_doc(successes, conditions=WEB_CONDITIONS, planned=planned, abort=abort)
    if videos:
        doc = doc.model_copy(update={"videos": videos})
    result = doc if state == State.SUCCEEDED or planned is not None else None
    assert report_final(db, s.id, 1, state, reason, result=result, log_tail=log_tail)
    db.commit()
    db.refresh(s)
    return s
