"""In a challenge with team mode on, a team's members share the daily and the concurrent quota,
also when they submit at the same moment; in per-user mode a team changes nothing."""

from __future__ import annotations

import threading

import pytest
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from server.challenges.quota import quota_use
from server.challenges.service import get_challenge
from server.kit.errors import QuotaExceeded
from server.models import Challenge, State, User, utcnow
from server.submissions.reports import report_final, report_state
from server.teams import service as teams
from testkit.factories import make_challenge, make_user, queue_submission


def _team(db: Session, *members: User) -> None:
    admin, *others = members
    team = teams.create_team(db, user=admin, name="grasp-lab", display_name="Grasp Lab")
    for member in others:
        invitation = teams.invite(db, admin=admin, team=team, username=member.username)
        teams.accept(db, user=member, invitation_id=invitation.id)
    db.commit()


def _finish(db: Session, submission_id: int) -> None:
    assert report_state(db, submission_id, 1, State.LAUNCHING, "starting")
    assert report_state(db, submission_id, 1, State.RUNNING, "evaluating")
    assert report_final(db, submission_id, 1, State.FAILED, "done")
    db.commit()


def test_members_share_the_daily_quota_in_team_mode(db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=2, quota_concurrent=5, teams=True)
    alice, bob, carol = (make_user(db, n) for n in ("alice", "bob", "carol"))
    _team(db, alice, bob)
    queue_submission(db, alice, challenge)
    queue_submission(db, bob, challenge)
    with pytest.raises(QuotaExceeded, match="team grasp-lab's daily quota of 2"):
        queue_submission(db, alice, challenge)
    use = quota_use(db, user=bob, challenge=challenge, now=utcnow())
    assert (use.per_day_used, use.team) == (2, "grasp-lab")
    queue_submission(db, carol, challenge)  # not in the team: her own quota


def test_members_share_the_concurrent_quota_in_team_mode(db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=5, quota_concurrent=1, teams=True)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    _team(db, alice, bob)
    first = queue_submission(db, alice, challenge)
    with pytest.raises(QuotaExceeded, match="still queued or running"):
        queue_submission(db, bob, challenge)
    _finish(db, first.id)
    assert queue_submission(db, bob, challenge).team_id is not None


def test_joining_or_leaving_a_team_hands_out_no_quota(db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=3, quota_concurrent=5, teams=True)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    queue_submission(db, bob, challenge)  # before joining: counts for the team he joins
    _team(db, alice, bob)
    queue_submission(db, bob, challenge)  # made in the team: stays the team's
    queue_submission(db, alice, challenge)
    with pytest.raises(QuotaExceeded):
        queue_submission(db, alice, challenge)
    teams.leave(db, user=bob)
    db.commit()
    # Leaving frees neither side: bob's own quota holds both of his, the team's the one he
    # made in it and alice's.
    assert quota_use(db, user=bob, challenge=challenge, now=utcnow()).per_day_used == 2
    assert quota_use(db, user=alice, challenge=challenge, now=utcnow()).per_day_used == 2


def test_per_user_mode_ignores_teams(db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=1, quota_concurrent=5)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    _team(db, alice, bob)
    queue_submission(db, alice, challenge)
    made = queue_submission(db, bob, challenge)
    assert made.team_id is not None  # recorded all the same: a later team mode counts it
    use = quota_use(db, user=alice, challenge=challenge, now=utcnow())
    assert (use.per_day_used, use.team) == (1, None)


# Postgres alone: SQLite runs one writer at a time, so there is no race to lose there.
@pytest.mark.parametrize("engine", ["postgres"], indirect=True)
def test_two_members_submitting_at_once_cannot_both_pass_the_quota(
    engine: Engine, committed_sessions: sessionmaker[Session]
) -> None:
    assert engine.dialect.name == "postgresql"
    with committed_sessions() as db:
        make_challenge(db, quota_per_day=10, quota_concurrent=1, teams=True)
        members = [make_user(db, n) for n in ("alice", "bob", "carol", "dave")]
        _team(db, *members)
        ids = [m.id for m in members]
    barrier = threading.Barrier(len(ids))
    outcomes: list[str] = []

    def attempt(user_id: int) -> None:
        with committed_sessions() as db:
            user = db.get(User, user_id)
            challenge: Challenge = get_challenge(db, slug="server-tiny")
            assert user is not None
            barrier.wait()
            try:
                queue_submission(db, user, challenge)
                db.commit()
                outcomes.append("accepted")
            except QuotaExceeded:
                db.rollback()
                outcomes.append("refused")

    threads = [threading.Thread(target=attempt, args=(i,)) for i in ids]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert sorted(outcomes) == ["accepted"] + ["refused"] * (len(ids) - 1)
