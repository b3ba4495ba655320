"""In team mode, flagging a team's best submission as a baseline moves it out of the team's row
into a baseline row of its own, and unflagging it moves it back, in one refresh each."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import Challenge, LeaderboardEntry, State, Submission, User
from server.submissions.reports import report_final, report_state
from server.submissions.service import edit
from server.teams import service as teams
from testkit.factories import make_challenge, make_user, queue_submission, result_doc


def _done(db: Session, user: User, challenge: Challenge, successes: list[bool]) -> Submission:
    s = queue_submission(db, user, challenge)
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=result_doc(successes))
    db.commit()
    return s


def _rows(db: Session) -> list[tuple[str | None, int, bool]]:
    found = db.execute(
        select(
            LeaderboardEntry.team_name, LeaderboardEntry.submission_id, LeaderboardEntry.baseline
        ).order_by(LeaderboardEntry.score.desc())
    ).all()
    return [(team, sid, baseline) for team, sid, baseline in found]


def test_a_teams_best_flagged_as_baseline_and_back(db: Session) -> None:
    admin, alice, bob = (
        make_user(db, "curator", admin=True),
        make_user(db, "alice"),
        make_user(db, "bob"),
    )
    team = teams.create_team(db, user=alice, name="grasp-lab", display_name="Grasp Lab")
    invitation = teams.invite(db, admin=alice, team=team, username="bob")
    teams.accept(db, user=bob, invitation_id=invitation.id)
    db.commit()
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20, teams=True)
    best = _done(db, bob, challenge, [True, True])
    other = _done(db, alice, challenge, [True, False])
    assert _rows(db) == [("grasp-lab", best.id, False)]
    edit(db, user=admin, submission=best, baseline=True)
    db.commit()
    assert _rows(db) == [(None, best.id, True), ("grasp-lab", other.id, False)]
    edit(db, user=admin, submission=best, baseline=False)
    db.commit()
    assert _rows(db) == [("grasp-lab", best.id, False)]
