"""The organizers' console pages: each for administrators only, the settings forms with their
successes and their problems by the field, the account actions and a disabled account shut
out of the pages, the filters of every submission, the audit records paged by id."""

from __future__ import annotations

import re
from datetime import UTC, datetime
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from server import audit
from server.console import pages as console_pages
from server.console import user_pages
from server.models import Challenge, Phase, State, User
from server.submissions import submit_pages
from testkit.factories import PASSWORD, make_challenge, make_user, queue_submission
from tests.server.test_challenge_rules import _challenge
from tests.web.helpers import browser, csrf_of, finished

PAGES = ["/admin", "/admin/challenges/server-tiny", "/admin/users", "/admin/audit"]


@pytest.fixture
def people(db: Session) -> dict[str, User]:
    return {
        "alice": make_user(db, "alice"),
        "bob": make_user(db, "bob", verified=False),
        "judge": make_user(db, "judge", admin=True),
    }


def _post(client: TestClient, page: str, action: str, **data: str) -> str:
    """Send the form of `page` that posts to `action`; the page it ends on."""
    token = csrf_of(client.get(page).text)
    r = client.post(action, data={"csrf_token": token, **data})
    if r.status_code == 303:
        r = client.get(r.headers["location"])
    assert r.status_code == 200, r.text
    return r.text


def test_console_pages_are_for_administrators_only(
    client: TestClient, tiny: Challenge, people: dict[str, User]
) -> None:
    judge, alice, anonymous = browser(client, "judge"), browser(client, "alice"), browser(client)
    pages = [*PAGES, f"/admin/users/{people['alice'].id}"]
    for page in pages:
        r = judge.get(page)
        assert r.status_code == 200, (page, r.text)
        assert 'aria-label="Console"' in r.text
        assert alice.get(page).status_code == 403, page
        r = anonymous.get(page)
        assert r.status_code == 303, page
        assert r.headers["location"].startswith("/login?next=")
    action = f"/admin/users/{people['bob'].id}/verify"
    r = alice.post(action, data={"csrf_token": csrf_of(alice.get("/account").text)})
    assert r.status_code == 403
    assert 'href="/admin"' in judge.get("/").text  # the nav's Console link
    assert 'href="/admin"' not in alice.get("/").text


def test_the_home_shows_phases_counts_stuck_ones_and_latest_records(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, User]
) -> None:
    finished(db, people["alice"], tiny, [True, False])
    running = queue_submission(db, people["alice"], tiny)
    running.state, running.updated_at = State.LAUNCHING, datetime(2020, 1, 1, tzinfo=UTC)
    db.commit()
    judge = browser(client, "judge")
    _post(
        judge,
        "/admin/challenges/server-tiny",
        "/admin/challenges/server-tiny/settings",
        quota_per_day="4",
        quota_concurrent="2",
    )
    home = judge.get("/admin").text
    assert "Server Tiny" in home
    assert re.search(r"<th scope=\"row\">dev</th><td><span class=\"badge badge-open\">open", home)
    assert "1 succeeded" in home
    assert "1 launching" in home
    assert "1 stuck" in home
    assert "challenge.settings" in home
    assert "quota_per_day: 3 → 4" in home


def test_challenge_settings_save_and_refuse_by_the_field(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, User]
) -> None:
    judge = browser(client, "judge")
    page, settings = "/admin/challenges/server-tiny", "/admin/challenges/server-tiny/settings"
    done = _post(judge, page, settings, quota_per_day="8", quota_concurrent="3", team_mode="on")
    assert "The challenge&#39;s settings are saved." in done
    db.expire_all()
    assert (tiny.quota_per_day, tiny.quota_concurrent, tiny.team_mode) == (8, 3, True)
    refused = _post(judge, page, settings, quota_per_day="0", quota_concurrent="many")
    assert 'id="quota_per_day-error"' in refused
    assert 'id="quota_concurrent-error"' in refused
    assert 'value="many"' in refused  # the form again as it was sent
    db.expire_all()
    assert tiny.quota_per_day == 8
    assert _post(judge, page, settings, quota_per_day="8", quota_concurrent="3")
    db.expire_all()
    assert tiny.team_mode is False  # unchecked: off


def _test_phase(db: Session, tiny: Challenge) -> Phase:
    db.expire_all()
    found = db.scalar(select(Phase).where(Phase.challenge_id == tiny.id, Phase.name == "test"))
    assert found is not None
    return found


def test_phase_dates_open_and_close_from_the_settings_page(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, User]
) -> None:
    judge = browser(client, "judge")
    page, base = "/admin/challenges/server-tiny", "/admin/challenges/server-tiny/phases/test"
    done = _post(judge, page, f"{base}/dates", opens_at="2090-01-01T10:00", closes_at="")
    assert "The phase&#39;s dates are saved." in done
    assert _test_phase(db, tiny).opens_at == datetime(2090, 1, 1, 10, tzinfo=UTC)
    assert "not yet open" in done
    refused = _post(
        judge, page, f"{base}/dates", opens_at="2090-01-01T10:00", closes_at="2089-01-01T00:00"
    )
    assert "must be after the opening date" in refused
    assert 'aria-invalid="true" aria-describedby="phase-2-closes-error"' in refused
    refused = _post(judge, page, f"{base}/dates", opens_at="soon", closes_at="")
    assert "a date and time like 2027-01-31T12:00 (UTC)" in refused
    assert "The phase is open." in _post(judge, page, f"{base}/open")
    assert _test_phase(db, tiny).is_open(datetime.now(UTC))
    refused = _post(judge, page, f"{base}/open")
    assert "is open already" in refused
    assert "The phase is closed" in _post(judge, page, f"{base}/close")
    assert not _test_phase(db, tiny).is_open(datetime.now(UTC))
    closed = _test_phase(db, tiny)
    assert closed.opens_at is not None
    assert closed.closes_at is not None
    as_shown = {
        name: f"{value:%Y-%m-%dT%H:%M}"
        for name, value in (("opens_at", closed.opens_at), ("closes_at", closed.closes_at))
    }
    closes_at = closed.closes_at
    assert "dates are saved" in _post(judge, page, f"{base}/dates", **as_shown)
    assert _test_phase(db, tiny).closes_at == closes_at  # sent back as shown: kept
    refused = _post(judge, page, f"{base}/publish")
    assert "has a public board: nothing to publish" in refused
    with_records = judge.get("/admin/audit?action=phase.open").text
    assert "phase.open" in with_records


def test_a_hidden_board_is_published_from_the_settings_page(
    client: TestClient, db: Session, tmp_path: Path, people: dict[str, User]
) -> None:
    _challenge(db, tmp_path)  # its test board is hidden
    judge = browser(client, "judge")
    page = "/admin/challenges/server-tiny"
    assert "Publish the board" in judge.get(page).text
    done = _post(judge, page, f"{page}/phases/test/publish")
    assert "The phase&#39;s board is public." in done
    assert "Publish the board" not in done


def test_an_admin_disables_an_account_which_is_shut_out_of_the_pages(
    client: TestClient, db: Session, tiny: Challenge, people: dict[str, User]
) -> None:
    alice_browser = browser(client, "alice")
    queued = queue_submission(db, people["alice"], tiny)
    db.commit()
    judge = browser(client, "judge")
    page = f"/admin/users/{people['alice'].id}"
    refused = _post(judge, page, f"{page}/disable", reason="  ")
    assert 'id="reason-error"' in refused
    assert "say why: a reason is required" in refused
    done = _post(judge, page, f"{page}/disable", reason="cheating on the test seeds")
    assert "The account is disabled" in done
    assert "cheating on the test seeds" in done  # its history
    db.expire_all()
    assert queued.state == State.CANCELLED

    r = alice_browser.get("/submissions")  # the session ended
    assert r.status_code == 303
    assert r.headers["location"].startswith("/login")
    form = csrf_of(alice_browser.get("/login").text)
    r = alice_browser.post(
        "/login", data={"login": "alice", "password": PASSWORD, "csrf_token": form}
    )
    assert r.status_code == 200
    assert "this account is disabled: cheating on the test seeds" in r.text

    assert "The account is enabled again." in _post(judge, page, f"{page}/enable")
    browser(client, "alice")  # logs in again


def test_verify_and_admin_rights_from_a_users_page_but_not_ones_own(
    client: TestClient, db: Session, people: dict[str, User]
) -> None:
    judge = browser(client, "judge")
    bob = f"/admin/users/{people['bob'].id}"
    assert "marked verified" in _post(judge, bob, f"{bob}/verify")
    assert "is an administrator now" in _post(judge, bob, f"{bob}/admin", admin="true")
    assert "no longer an administrator" in _post(judge, bob, f"{bob}/admin", admin="false")
    mine = f"/admin/users/{people['judge'].id}"
    assert "another administrator changes its rights" in judge.get(mine).text
    refused = _post(judge, mine, f"{mine}/admin", admin="false")
    assert "your own account" in refused
    refused = _post(judge, mine, f"{mine}/disable", reason="oops")
    assert "your own account" in refused
    history = judge.get(bob).text
    for action in ("user.verify", "user.grant_admin", "user.revoke_admin"):
        assert action in history


def test_the_user_list_searches_and_pages(
    client: TestClient, db: Session, people: dict[str, User], monkeypatch: pytest.MonkeyPatch
) -> None:
    judge = browser(client, "judge")
    page = judge.get("/admin/users?q=BO").text
    assert ">bob</a>" in page
    assert ">alice</a>" not in page
    assert "unverified" in page
    monkeypatch.setattr(user_pages, "PER_PAGE", 2)
    first = judge.get("/admin/users?q=example").text
    assert "Page 1 of 2" in first
    assert 'href="/admin/users?q=example&amp;page=2"' in first
    second = judge.get("/admin/users?q=example&page=2").text
    assert ">alice</a>" in second  # the oldest


def test_every_submission_filters_by_user_challenge_phase_and_state_kept_in_paging(
    client: TestClient, db: Session, people: dict[str, User], monkeypatch: pytest.MonkeyPatch
) -> None:
    roomy = make_challenge(db, quota_per_day=20, quota_concurrent=20)
    mine = [queue_submission(db, people["alice"], roomy).id for _ in range(3)]
    test_one = queue_submission(db, people["alice"], roomy, "test").id
    bobs = queue_submission(db, people["judge"], roomy).id
    done = finished(db, people["alice"], roomy, [True]).id
    db.commit()
    judge = browser(client, "judge")

    def shown(query: str) -> set[int]:
        text = judge.get(f"/admin/submissions?{query}").text
        return {int(n) for n in re.findall(r'<a href="/submissions/(\d+)">#', text)}

    assert shown("user=ALICE") == {*mine, test_one, done}
    assert shown("user=alice&phase=test") == {test_one}
    assert shown("user=alice&state=succeeded") == {done}
    assert shown("challenge=server-tiny&phase=dev&state=queued") == {*mine, bobs}
    assert shown("user=nobody") == set()
    assert "no user named &#39;nobody&#39;" in judge.get("/admin/submissions?user=nobody").text
    assert "no challenge &#39;nope&#39;" in judge.get("/admin/submissions?challenge=nope").text
    monkeypatch.setattr(submit_pages, "PER_PAGE", 2)
    first = judge.get("/admin/submissions?user=alice&phase=dev&state=queued").text
    assert 'href="/admin/submissions?user=alice&amp;phase=dev&amp;state=queued&amp;page=2"' in first
    assert shown("user=alice&phase=dev&state=queued&page=2") == {mine[0]}
    assert "selected>dev</option>" in first


def test_audit_records_filter_by_challenge_and_action_and_page_by_id(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    people: dict[str, User],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for n in range(5):
        audit.record(
            db,
            by=people["judge"],
            action="phase.open" if n % 2 else "challenge.settings",
            target_kind="challenge",
            target_id=tiny.id,
            challenge_id=tiny.id if n < 4 else None,
            reason=f"reason number {n}",
        )
    db.commit()
    ids = [r.id for r in audit.records(db)]  # newest first
    monkeypatch.setattr(console_pages, "RECORDS_PER_PAGE", 2)
    judge = browser(client, "judge")
    first = judge.get("/admin/audit?challenge=server-tiny").text
    assert "reason number 3" in first
    assert "reason number 2" in first
    assert "reason number 4" not in first  # no challenge
    assert f'href="/admin/audit?challenge=server-tiny&amp;before={ids[2]}"' in first
    second = judge.get(f"/admin/audit?challenge=server-tiny&before={ids[2]}").text
    assert "reason number 1" in second
    assert "reason number 0" in second
    assert f'href="/admin/audit?challenge=server-tiny&amp;before={ids[4]}"' in second
    third = judge.get(f"/admin/audit?challenge=server-tiny&before={ids[4]}").text
    assert "challenge.load" in third  # the oldest: the challenge's load, from the command line
    assert "Older" not in third
    opened = judge.get("/admin/audit?action=phase.open").text
    assert "reason number 3" in opened
    assert "reason number 2" not in opened
    assert "No audit record matches" in judge.get("/admin/audit?challenge=nope").text
