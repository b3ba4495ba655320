"""Teams under concurrent changes, on Postgres (SQLite runs one writer at a time, so there is
no race to lose there): a team never loses its admin, a dissolution racing an accept or an
invitation answers 404, twin invitations and twin team names answer 409, and a team dissolving
while a worker reports a result for one of its submissions deadlocks nothing."""

from __future__ import annotations

import threading
from collections.abc import Callable

import pytest
from sqlalchemy import Engine, select
from sqlalchemy.orm import Session, sessionmaker

from server.challenges.service import get_challenge
from server.kit.errors import AppError
from server.models import LeaderboardEntry, State, Team, TeamMember, User
from server.submissions.reports import report_final, report_state
from server.teams import service as teams
from testkit.factories import make_challenge, make_user, queue_submission, result_doc

ROUNDS = 8
postgres = pytest.mark.parametrize("engine", ["postgres"], indirect=True)


def _team(db: Session, name: str, *members: User) -> Team:
    admin, *others = members
    team = teams.create_team(db, user=admin, name=name, display_name=name.title())
    for member in others:
        invitation = teams.invite(db, admin=admin, team=team, username=member.username)
        teams.accept(db, user=member, invitation_id=invitation.id)
    db.commit()
    return team


def _at_once(sessions: sessionmaker[Session], *actions: Callable[[Session], str]) -> list[str]:
    """Run each action in its own session and thread, released together; each commits and
    names its outcome, or names the AppError it raised; anything else is re-raised here."""
    barrier = threading.Barrier(len(actions))
    outcomes: list[str] = [""] * len(actions)
    failures: list[BaseException] = []

    def run(index: int, action: Callable[[Session], str]) -> None:
        with sessions() as db:
            try:
                barrier.wait(timeout=60)
                outcomes[index] = action(db)
                db.commit()
            except AppError as exc:
                db.rollback()
                outcomes[index] = str(exc.status)
            except BaseException as exc:
                failures.append(exc)

    threads = [threading.Thread(target=run, args=(i, a)) for i, a in enumerate(actions)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads)
    if failures:
        raise failures[0]
    return outcomes


def _user(db: Session, user_id: int) -> User:
    user = db.get(User, user_id)
    assert user is not None
    return user


def _admins(db: Session, team_id: int) -> list[bool]:
    return list(db.scalars(select(TeamMember.is_admin).where(TeamMember.team_id == team_id)))


@postgres
def test_the_admin_and_the_next_in_line_leaving_at_once_leave_an_admin(
    engine: Engine, committed_sessions: sessionmaker[Session]
) -> None:
    for n in range(ROUNDS):
        _two_leave_at_once(committed_sessions, n)


def _two_leave_at_once(committed_sessions: sessionmaker[Session], n: int) -> None:
    with committed_sessions() as db:
        a, b, c = (make_user(db, f"r{n}-{who}") for who in "abc")
        team_id = _team(db, f"leave-{n}", a, b, c).id
    ids = a.id, b.id

    def leave(user_id: int) -> Callable[[Session], str]:
        return lambda db: str(teams.leave(db, user=_user(db, user_id)) is not None)

    assert _at_once(committed_sessions, *(leave(i) for i in ids)) == ["True", "True"]
    with committed_sessions() as db:
        assert _admins(db, team_id) == [True], f"round {n}: carol is no admin"


@postgres
def test_removing_while_leaving_as_admin_leaves_one_admin(
    engine: Engine, committed_sessions: sessionmaker[Session]
) -> None:
    for n in range(ROUNDS):
        _remove_while_leaving(committed_sessions, n)


def _remove_while_leaving(committed_sessions: sessionmaker[Session], n: int) -> None:
    with committed_sessions() as db:
        a, b, c = (make_user(db, f"r{n}-{who}") for who in "abc")
        team = _team(db, f"remove-{n}", a, b, c)
    team_id, name = team.id, team.name

    def remove(db: Session) -> str:
        found = teams.get_team(db, name=name)
        teams.remove(db, admin=_user(db, a.id), team=found, username=b.username)
        return "removed"

    def leave(db: Session) -> str:
        return str(teams.leave(db, user=_user(db, a.id)) is not None)

    outcomes = _at_once(committed_sessions, remove, leave)
    # Removing first, then leaving, or leaving first: the remove is refused (403).
    assert outcomes in (["removed", "True"], ["403", "True"]), outcomes
    with committed_sessions() as db:
        assert _admins(db, team_id).count(True) == 1, f"round {n}: {outcomes}"


@postgres
def test_accepting_or_inviting_while_the_team_dissolves_answers_404(
    engine: Engine, committed_sessions: sessionmaker[Session]
) -> None:
    for n in range(ROUNDS):
        _accept_and_invite_while_dissolving(committed_sessions, n)


def _accept_and_invite_while_dissolving(committed_sessions: sessionmaker[Session], n: int) -> None:
    with committed_sessions() as db:
        a, b, c = (make_user(db, f"r{n}-{who}") for who in "abc")
        team = _team(db, f"gone-{n}", a)
        invitation_id = teams.invite(db, admin=a, team=team, username=b.username).id
        db.commit()
    name = team.name

    def accept(db: Session) -> str:
        teams.accept(db, user=_user(db, b.id), invitation_id=invitation_id)
        return "joined"

    def invite(db: Session) -> str:
        found = teams.get_team(db, name=name)
        teams.invite(db, admin=_user(db, a.id), team=found, username=c.username)
        return "invited"

    def leave(db: Session) -> str:
        return "kept" if teams.leave(db, user=_user(db, a.id)) is not None else "dissolved"

    outcomes = _at_once(committed_sessions, accept, invite, leave)
    assert outcomes[0] in ("joined", "404"), outcomes
    # Invited before the leave, or refused after it: 404 once dissolved, 403 once bob
    # has taken alice's place as admin.
    assert outcomes[1] in ("invited", "404", "403"), outcomes
    # Joined before the leave: bob is left as the team's admin; otherwise it dissolved.
    assert outcomes[2] == ("kept" if outcomes[0] == "joined" else "dissolved"), outcomes
    with committed_sessions() as db:
        assert _admins(db, team.id) == ([True] if outcomes[0] == "joined" else [])


@postgres
def test_twin_invitations_and_twin_team_names_answer_409(
    engine: Engine, committed_sessions: sessionmaker[Session]
) -> None:
    for n in range(ROUNDS):
        _twins(committed_sessions, n)


def _twins(committed_sessions: sessionmaker[Session], n: int) -> None:
    with committed_sessions() as db:
        a, b, c, d = (make_user(db, f"r{n}-{who}") for who in "abcd")
        name = _team(db, f"twin-{n}", a).name

    def invite(db: Session) -> str:
        found = teams.get_team(db, name=name)
        teams.invite(db, admin=_user(db, a.id), team=found, username=b.username)
        return "invited"

    assert sorted(_at_once(committed_sessions, invite, invite)) == ["409", "invited"]

    def create(user_id: int) -> Callable[[Session], str]:
        def run(db: Session) -> str:
            teams.create_team(db, user=_user(db, user_id), name=f"new-{n}", display_name="N")
            return "created"

        return run

    outcomes = _at_once(committed_sessions, create(c.id), create(d.id))
    assert sorted(outcomes) == ["409", "created"]


@postgres
def test_a_team_dissolving_while_a_result_of_its_arrives_deadlocks_nothing(
    engine: Engine, committed_sessions: sessionmaker[Session]
) -> None:
    with committed_sessions() as db:
        make_challenge(db, quota_per_day=100, quota_concurrent=100, teams=True)
    for n in range(ROUNDS):
        _dissolve_while_reporting(committed_sessions, n)


def _dissolve_while_reporting(committed_sessions: sessionmaker[Session], n: int) -> None:
    with committed_sessions() as db:
        challenge = get_challenge(db, slug="server-tiny")
        a, b = make_user(db, f"r{n}-a"), make_user(db, f"r{n}-b")
        team_id = _team(db, f"deadlock-{n}", a, b).id
        # Both submit in the team; bob leaves; alice is its last member.
        made = [queue_submission(db, who, challenge).id for who in (a, b)]
        for submission_id in made:
            assert report_state(db, submission_id, 1, State.LAUNCHING, "starting")
            assert report_state(db, submission_id, 1, State.RUNNING, "evaluating")
        db.commit()
        teams.leave(db, user=b)
        db.commit()

    def report(submission_id: int) -> Callable[[Session], str]:
        def run(db: Session) -> str:
            done = result_doc([True, False])
            assert report_final(db, submission_id, 1, State.SUCCEEDED, "done", result=done)
            return "reported"

        return run

    def leave(db: Session) -> str:
        return "kept" if teams.leave(db, user=_user(db, a.id)) is not None else "dissolved"

    outcomes = _at_once(committed_sessions, report(made[1]), report(made[0]), leave)
    assert outcomes == ["reported", "reported", "dissolved"]
    with committed_sessions() as db:
        rows = db.execute(
            select(LeaderboardEntry.user_id, LeaderboardEntry.team_id).where(
                LeaderboardEntry.user_id.in_([a.id, b.id])
            )
        ).all()
        # The dissolved team's submissions are their submitters' own: one row each.
        assert sorted(rows) == sorted([(a.id, None), (b.id, None)])
        assert db.get(Team, team_id) is not None  # kept, so submissions still point at it
