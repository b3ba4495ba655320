"""Audit records: written beside the change they record, read newest first, reasons checked."""

from __future__ import annotations

import getpass

import pytest
from sqlalchemy.orm import Session

from server import audit
from server.kit.errors import Invalid
from server.models import AuditRecord, Challenge, User


def _admin(db: Session) -> User:
    user = User(username="olga", email="olga@example.org", password_hash="x", is_admin=True)
    db.add(user)
    db.flush()
    return user


def _challenge(db: Session) -> Challenge:
    challenge = Challenge(slug="c", title="C", suite_yaml="", suite_hash="0" * 64)
    db.add(challenge)
    db.flush()
    return challenge


def test_a_record_names_the_admin_or_the_command_line_login(db: Session) -> None:
    olga = _admin(db)
    audit.record(db, by=olga, action="submission.hide", target_kind="submission", target_id=7)
    audit.record(db, by=None, action="phase.close", target_kind="phase", target_id=1)
    db.flush()

    cli, web = audit.records(db)

    assert (web.actor, web.actor_id, web.action, web.target_id) == (
        "olga",
        olga.id,
        "submission.hide",
        7,
    )
    assert (cli.actor, cli.actor_id) == (f"cli:{getpass.getuser()}", None)
    assert web.at.tzinfo is not None


def test_records_filter_and_page_newest_first(db: Session) -> None:
    olga = _admin(db)
    challenge = _challenge(db)
    for n in range(5):
        audit.record(
            db,
            by=olga,
            action="submission.rerun" if n % 2 else "submission.hide",
            target_kind="submission",
            target_id=n,
            challenge_id=challenge.id if n < 3 else None,
            reason=f"because {n}",
            detail={"n": n},
        )
    db.flush()

    assert [r.target_id for r in audit.records(db)] == [4, 3, 2, 1, 0]
    assert [r.target_id for r in audit.records(db, challenge_id=challenge.id)] == [2, 1, 0]
    assert [r.target_id for r in audit.records(db, action="submission.rerun")] == [3, 1]
    first = audit.records(db, limit=2)
    rest = audit.records(db, before_id=first[-1].id)
    assert [r.target_id for r in first + rest] == [4, 3, 2, 1, 0]
    assert audit.records(db, target_kind="submission", target_id=3)[0].detail == {"n": 3}


def test_a_deleted_admin_or_challenge_leaves_the_record_and_its_name(db: Session) -> None:
    olga = _admin(db)
    challenge = _challenge(db)
    audit.record(
        db,
        by=olga,
        action="challenge.settings",
        target_kind="challenge",
        target_id=challenge.id,
        challenge_id=challenge.id,
    )
    db.flush()
    db.delete(olga)
    db.delete(challenge)
    db.flush()
    db.expire_all()

    (kept,) = db.query(AuditRecord).all()
    assert (kept.actor, kept.actor_id, kept.challenge_id) == ("olga", None, None)


@pytest.mark.parametrize("text", ["", "   ", None])
def test_an_action_that_affects_someone_requires_a_reason(text: str | None) -> None:
    with pytest.raises(Invalid) as raised:
        audit.reason_of(text, required=True)
    assert raised.value.fields == {"reason": "required"}
    assert audit.reason_of(text, required=False) == ""


def test_a_reason_is_stripped_and_bounded() -> None:
    assert audit.reason_of("  copied the seeds \n", required=True) == "copied the seeds"
    assert len(audit.reason_of("x" * audit.REASON_MAX, required=True)) == audit.REASON_MAX
    with pytest.raises(Invalid, match="longer than 2000"):
        audit.reason_of("x" * (audit.REASON_MAX + 1), required=True)
