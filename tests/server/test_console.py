"""The organizers' settings and accounts through the API (`PATCH /api/v1/challenges/...`,
`/api/v1/admin/users/...`): each change and its refusals, a disabled account locked out of
every door with its queued work cancelled, and the audit record each action leaves."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server import audit
from server.accounts import service as accounts
from server.kit.deps import CSRF_HEADER
from server.kit.settings import Settings
from server.models import AuditRecord, Challenge, Phase, State, Submission, Transition, User
from server.registry import service as registry
from testkit.factories import PASSWORD, make_challenge, make_user, queue_submission, token_for

TINY = "/api/v1/challenges/server-tiny"


@pytest.fixture
def ready(sessions: sessionmaker[Session]) -> None:
    with sessions() as db:
        make_challenge(db, quota_per_day=5, quota_concurrent=2)
        make_user(db, "alice")
        make_user(db, "organizer", admin=True)


def _latest(sessions: sessionmaker[Session], action: str) -> AuditRecord:
    with sessions() as db:
        found = audit.records(db, action=action, limit=1)
        assert found, f"no {action} record"
        return found[0]


def _phase(sessions: sessionmaker[Session], name: str) -> Phase:
    with sessions() as db:
        phase = db.scalar(
            select(Phase).join(Challenge).where(Challenge.slug == "server-tiny", Phase.name == name)
        )
        assert phase is not None
        return phase


def test_an_admin_changes_quotas_and_team_mode_and_the_record_holds_old_and_new(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    admin = token_for(client, "organizer")
    r = client.patch(TINY, json={"quota_per_day": 9, "team_mode": True}, headers=admin)
    assert r.status_code == 200, r.text
    body = r.json()
    assert (body["quota_per_day"], body["quota_concurrent"], body["team_mode"]) == (9, 2, True)
    record = _latest(sessions, "challenge.settings")
    assert (record.actor, record.target_kind) == ("organizer", "challenge")
    assert record.detail == {
        "old": {"quota_per_day": 5, "team_mode": False},
        "new": {"quota_per_day": 9, "team_mode": True},
    }
    again = client.patch(TINY, json={"quota_per_day": 9}, headers=admin)
    assert again.status_code == 200
    with sessions() as db:  # nothing changed: nothing recorded
        assert len(audit.records(db, action="challenge.settings")) == 1


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"quota_per_day": 0}, "quota_per_day"),
        ({"quota_concurrent": 10_001}, "quota_concurrent"),
        ({"quota_per_day": "3"}, "quota_per_day"),
    ],
)
def test_a_quota_out_of_range_is_refused_by_its_field(
    client: TestClient, ready: None, body: dict[str, object], field: str
) -> None:
    r = client.patch(TINY, json=body, headers=token_for(client, "organizer"))
    assert r.status_code == 422, r.text
    assert field in r.json()["error"]["fields"]


def test_only_admins_change_settings_or_open_phases(client: TestClient, ready: None) -> None:
    alice = token_for(client, "alice")
    assert client.patch(TINY, json={"quota_per_day": 9}, headers=alice).status_code == 403
    assert client.patch(TINY, json={"quota_per_day": 9}).status_code == 401
    dates = {"closes_at": "2090-01-01T00:00:00Z"}
    assert client.patch(f"{TINY}/phases/dev", json=dates, headers=alice).status_code == 403
    assert client.post(f"{TINY}/phases/dev/open", headers=alice).status_code == 403


def test_phase_dates_move_clear_and_read_a_date_without_zone_as_utc(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    admin = token_for(client, "organizer")
    body = {"opens_at": "2090-01-01T09:00", "closes_at": "2090-02-01T00:00:00+02:00"}
    r = client.patch(f"{TINY}/phases/test", json=body, headers=admin)
    assert r.status_code == 200, r.text
    test = _phase(sessions, "test")
    assert test.opens_at == datetime(2090, 1, 1, 9, tzinfo=UTC)
    assert test.closes_at == datetime(2090, 1, 31, 22, tzinfo=UTC)
    record = _latest(sessions, "phase.settings")
    assert record.detail is not None
    assert record.detail["phase"] == "test"
    assert record.detail["old"] == {"opens_at": None, "closes_at": None}
    assert record.detail["new"]["closes_at"] == "2090-01-31T22:00:00+00:00"
    r = client.patch(f"{TINY}/phases/test", json={"opens_at": None}, headers=admin)
    assert r.status_code == 200, r.text
    test = _phase(sessions, "test")
    assert test.opens_at is None  # null clears it; the close date left out stays
    assert test.closes_at == datetime(2090, 1, 31, 22, tzinfo=UTC)


@pytest.mark.parametrize(
    ("body", "field", "words"),
    [
        (
            {"opens_at": "2090-02-01T00:00Z", "closes_at": "2090-01-01T00:00Z"},
            "closes_at",
            "after the opening",
        ),
        ({"closes_at": "2020-01-01T00:00Z"}, "closes_at", "in the past"),
        ({"opens_at": "0001-01-01T00:00Z"}, "opens_at", "from 1970"),
        ({"opens_at": "tomorrow"}, "opens_at", ""),
    ],
)
def test_phase_dates_that_make_no_sense_are_refused_by_their_field(
    client: TestClient, ready: None, body: dict[str, object], field: str, words: str
) -> None:
    r = client.patch(f"{TINY}/phases/test", json=body, headers=token_for(client, "organizer"))
    assert r.status_code == 422, r.text
    assert words in r.json()["error"]["fields"][field]


def test_an_unknown_phase_or_challenge_is_named(client: TestClient, ready: None) -> None:
    admin = token_for(client, "organizer")
    r = client.patch(f"{TINY}/phases/final", json={"opens_at": None}, headers=admin)
    assert r.status_code == 422
    assert "it has: dev, test" in r.json()["error"]["message"]
    r = client.patch("/api/v1/challenges/nope", json={"quota_per_day": 2}, headers=admin)
    assert r.status_code == 404


def test_open_now_opens_an_upcoming_phase_and_reopens_a_closed_one(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    admin = token_for(client, "organizer")
    later = (datetime.now(UTC) + timedelta(days=3)).isoformat()
    client.patch(f"{TINY}/phases/test", json={"opens_at": later}, headers=admin)
    r = client.post(f"{TINY}/phases/test/open", headers=admin)
    assert r.status_code == 200, r.text
    assert next(p for p in r.json()["phases"] if p["name"] == "test")["open"] is True
    assert client.post(f"{TINY}/phases/test/open", headers=admin).status_code == 409
    assert client.post(f"{TINY}/phases/test/close", headers=admin).status_code == 200
    r = client.post(f"{TINY}/phases/test/open", headers=admin)
    test = next(p for p in r.json()["phases"] if p["name"] == "test")
    assert (test["open"], test["closes_at"]) == (True, None)
    record = _latest(sessions, "phase.open")
    assert record.detail is not None
    assert record.detail["new"] == {"closes_at": None}


# Accounts ---------------------------------------------------------------------------------------


def _user(sessions: sessionmaker[Session], name: str) -> User:
    with sessions() as db:
        user = db.scalar(select(User).where(User.username == name))
        assert user is not None
        return user


def _disable(client: TestClient, user_id: int, reason: str = "spam") -> dict[str, object]:
    r = client.post(
        f"/api/v1/admin/users/{user_id}/disable",
        json={"reason": reason},
        headers=token_for(client, "organizer"),
    )
    assert r.status_code == 200, r.text
    body: dict[str, object] = r.json()
    return body


def test_a_disabled_account_cannot_log_in_use_its_token_or_its_session(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    token = token_for(client, "alice")
    r = client.post("/api/v1/session", json={"login": "alice", "password": PASSWORD})
    assert r.status_code == 200, r.text
    assert client.get("/api/v1/me").status_code == 200  # the cookie works
    _disable(client, _user(sessions, "alice").id, reason="  shared an account  ")  # a token

    assert client.get("/api/v1/me").status_code == 401  # the session ended
    r = client.get("/api/v1/me", headers=token)
    assert r.status_code == 403
    assert r.json()["error"] == {
        "code": "account_disabled",
        "message": "this account is disabled: shared an account",
        "fields": {},
    }
    r = client.post("/api/v1/session", json={"login": "alice", "password": PASSWORD})
    assert r.status_code == 403
    assert r.json()["error"]["message"] == "this account is disabled: shared an account"
    wrong = client.post("/api/v1/session", json={"login": "alice", "password": "not it at all"})
    assert wrong.status_code == 401  # only the password's holder learns it is disabled


def test_disabling_cancels_the_accounts_queued_work_and_enabling_lets_it_back_in(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    with sessions() as db:
        alice = db.scalar(select(User).where(User.username == "alice"))
        tiny = db.scalar(select(Challenge).where(Challenge.slug == "server-tiny"))
        assert alice is not None
        assert tiny is not None
        db.refresh(tiny, ["phases"])
        queued = [queue_submission(db, alice, tiny).id for _ in range(2)]
        db.commit()
    body = _disable(client, alice.id)
    assert body["cancelled"] == queued
    assert body["disabled_reason"] == "spam"
    with sessions() as db:
        states = db.scalars(select(Submission.state).where(Submission.id.in_(queued))).all()
        assert set(states) == {State.CANCELLED}
        reasons = db.scalars(
            select(Transition.reason).where(
                Transition.submission_id.in_(queued), Transition.to_state == State.CANCELLED
            )
        ).all()
        assert reasons == ["cancelled: an administrator disabled the account"] * 2
    record = _latest(sessions, "user.disable")
    assert (record.target_id, record.reason, record.actor) == (alice.id, "spam", "organizer")

    admin = token_for(client, "organizer")
    r = client.post(f"/api/v1/admin/users/{alice.id}/enable", json={}, headers=admin)
    assert r.status_code == 200, r.text
    assert r.json()["disabled_at"] is None
    detail = _latest(sessions, "user.enable").detail
    assert detail is not None
    assert detail["disabled_reason"] == "spam"
    token_for(client, "alice")  # logs in again


def test_disabling_needs_a_reason_and_never_ones_own_account(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    admin = token_for(client, "organizer")
    alice, organizer = _user(sessions, "alice"), _user(sessions, "organizer")
    r = client.post(f"/api/v1/admin/users/{alice.id}/disable", json={}, headers=admin)
    assert r.status_code == 422
    assert r.json()["error"]["fields"] == {"reason": "required"}
    r = client.post(
        f"/api/v1/admin/users/{organizer.id}/disable", json={"reason": "x"}, headers=admin
    )
    assert r.status_code == 403
    assert "your own account" in r.json()["error"]["message"]
    _disable(client, alice.id)
    r = client.post(f"/api/v1/admin/users/{alice.id}/disable", json={"reason": "x"}, headers=admin)
    assert r.status_code == 409
    r = client.post("/api/v1/admin/users/999999/disable", json={"reason": "x"}, headers=admin)
    assert r.status_code == 404


def test_an_admin_verifies_an_address_and_grants_and_revokes_admin_rights_not_their_own(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    with sessions() as db:
        make_user(db, "newbie", verified=False)
    newbie, organizer = _user(sessions, "newbie"), _user(sessions, "organizer")
    admin = token_for(client, "organizer")
    r = client.post(f"/api/v1/admin/users/{newbie.id}/verify", headers=admin)
    assert (r.status_code, r.json()["email_verified"]) == (200, True)
    assert client.post(f"/api/v1/admin/users/{newbie.id}/verify", headers=admin).status_code == 409
    r = client.put(f"/api/v1/admin/users/{newbie.id}/admin", headers=admin)
    assert (r.status_code, r.json()["is_admin"]) == (200, True)
    r = client.delete(f"/api/v1/admin/users/{newbie.id}/admin", headers=admin)
    assert (r.status_code, r.json()["is_admin"]) == (200, False)
    assert (
        client.delete(f"/api/v1/admin/users/{organizer.id}/admin", headers=admin).status_code == 403
    )
    with sessions() as db:
        actions = [r.action for r in audit.records(db, target_kind="user", target_id=newbie.id)]
    assert actions == ["user.revoke_admin", "user.grant_admin", "user.verify"]
    alice = token_for(client, "alice")
    assert client.put(f"/api/v1/admin/users/{newbie.id}/admin", headers=alice).status_code == 403


def test_the_user_list_searches_names_and_addresses_pages_and_counts_submissions(
    client: TestClient, sessions: sessionmaker[Session], ready: None
) -> None:
    with sessions() as db:
        for name in ("carol", "carl_x", "dave"):
            make_user(db, name)
        alice = db.scalar(select(User).where(User.username == "alice"))
        tiny = db.scalar(select(Challenge).where(Challenge.slug == "server-tiny"))
        assert alice is not None
        assert tiny is not None
        db.refresh(tiny, ["phases"])
        queue_submission(db, alice, tiny)
        db.commit()
    admin = token_for(client, "organizer")
    r = client.get("/api/v1/admin/users", params={"q": "CAR"}, headers=admin)
    assert [u["username"] for u in r.json()["items"]] == ["carl_x", "carol"]
    r = client.get("/api/v1/admin/users", params={"q": "_"}, headers=admin)
    assert [u["username"] for u in r.json()["items"]] == ["carl_x"]  # not a wildcard
    r = client.get("/api/v1/admin/users", params={"q": "alice@example"}, headers=admin)
    assert [(u["username"], u["submissions"]) for u in r.json()["items"]] == [("alice", 1)]
    r = client.get("/api/v1/admin/users", params={"per_page": 2, "page": 2}, headers=admin)
    assert r.json()["total"] == 5
    assert [u["username"] for u in r.json()["items"]] == ["carol", "organizer"]
    assert client.get("/api/v1/admin/users", headers=token_for(client, "alice")).status_code == 403


def test_a_cookie_session_needs_the_csrf_header_to_change_settings(
    client: TestClient, ready: None
) -> None:
    r = client.post("/api/v1/session", json={"login": "organizer", "password": PASSWORD})
    csrf = r.json()["csrf_token"]
    assert client.patch(TINY, json={"quota_per_day": 4}).status_code == 403
    r = client.patch(TINY, json={"quota_per_day": 4}, headers={CSRF_HEADER: csrf})
    assert r.status_code == 200, r.text


def test_the_registry_refuses_a_disabled_accounts_token_saying_why(
    db: Session, settings: Settings
) -> None:
    alice = make_user(db, "alice")
    _, plaintext = accounts.create_token(db, user=alice, name="podman")
    db.commit()
    grantee = registry.authenticate(db, settings=settings, username="alice", password=plaintext)
    assert grantee.subject == "alice"
    accounts.disable_user(db, user=alice, by=None, reason="spam")
    with pytest.raises(registry.RegistryUnauthorized, match="this account is disabled: spam"):
        registry.authenticate(db, settings=settings, username="alice", password=plaintext)
