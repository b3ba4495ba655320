"""Leaderboard rows per team in team mode (the team's best submission made in it, its name
linking to its page, who submitted), recomputed when membership changes; per-user mode as it
was; each row's method, paper and code links in the API, the CSV, the page and the terminal."""

from __future__ import annotations

import csv
import io

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from manieval.render import leaderboard_table, stdout
from server.challenges.service import set_team_mode
from server.models import Challenge, State, Submission, User, team_of
from server.submissions.reports import report_final, report_state
from server.teams import service as teams
from testkit.factories import make_challenge, make_user, queue_submission, result_doc

BOARD = "/api/v1/challenges/server-tiny/leaderboard?phase=dev"


def _done(
    db: Session, user: User, challenge: Challenge, successes: list[bool], **method: str
) -> Submission:
    s = queue_submission(db, user, challenge)
    for name, value in method.items():
        setattr(s, name, value)
    db.flush()
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=result_doc(successes))
    db.commit()
    return s


def _join(db: Session, admin: User, member: User) -> None:
    team = team_of(db, user_id=admin.id)
    if team is None:
        team = teams.create_team(db, user=admin, name="grasp-lab", display_name="Grasp Lab")
    invitation = teams.invite(db, admin=admin, team=team, username=member.username)
    teams.accept(db, user=member, invitation_id=invitation.id)
    db.commit()


def _rows(client: TestClient) -> list[tuple[str | None, str, float]]:
    items = client.get(BOARD).json()["items"]
    return [(r["team"], r["username"], r["score"]) for r in items]


def test_team_mode_shows_one_row_per_team_with_its_best(client: TestClient, db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20, teams=True)
    alice, bob, carol = (make_user(db, n) for n in ("alice", "bob", "carol"))
    _join(db, alice, bob)
    _done(db, alice, challenge, [True, False])
    _done(db, bob, challenge, [True, True])
    _done(db, carol, challenge, [False, False])
    assert _rows(client) == [("grasp-lab", "bob", 1.0), (None, "carol", 0.0)]
    (team_row,) = [r for r in client.get(BOARD).json()["items"] if r["team"]]
    assert team_row["team_display_name"] == "Grasp Lab"

    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    # The handle beside the display name: a display name alone could pass for another's.
    assert (
        '<a class="team-name" href="/teams/grasp-lab">Grasp Lab</a> '
        '<span class="muted team-handle">(grasp-lab)</span>'
    ) in html
    assert "by <a href=" in html
    text = client.get(BOARD + "&format=csv").text
    header, *rows = csv.reader(io.StringIO(text))
    assert rows[0][header.index("team")] == "grasp-lab"
    assert rows[0][header.index("team_display_name")] == "Grasp Lab"


def test_membership_changes_recompute_the_rows(client: TestClient, db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20, teams=True)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    _done(db, bob, challenge, [True, False])  # before joining: bob's own
    assert _rows(client) == [(None, "bob", 0.5)]
    _join(db, alice, bob)
    assert _rows(client) == []  # in a team: no row of his own; the team made nothing yet
    _done(db, bob, challenge, [False, False])
    assert _rows(client) == [("grasp-lab", "bob", 0.0)]
    teams.leave(db, user=bob)
    db.commit()
    # Leaving moves bob back to his own row; what he made in the team stays the team's.
    assert _rows(client) == [(None, "bob", 0.5), ("grasp-lab", "bob", 0.0)]
    teams.leave(db, user=alice)  # the last member: the team is dissolved
    db.commit()
    assert _rows(client) == [(None, "bob", 0.5)]


def test_removing_a_member_recomputes_the_rows(client: TestClient, db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20, teams=True)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    _done(db, bob, challenge, [True, False])  # bob's own
    _join(db, alice, bob)
    _done(db, bob, challenge, [True, True])  # the team's
    assert _rows(client) == [("grasp-lab", "bob", 1.0)]
    team = teams.get_team(db, name="grasp-lab")
    teams.remove(db, admin=alice, team=team, username="bob")
    db.commit()
    assert _rows(client) == [("grasp-lab", "bob", 1.0), (None, "bob", 0.5)]


def test_a_team_dissolving_while_a_former_member_is_in_another(
    client: TestClient, db: Session
) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20, teams=True)
    alice, bob, carol = (make_user(db, n) for n in ("alice", "bob", "carol"))
    _join(db, alice, bob)
    _done(db, bob, challenge, [True, True])  # made in grasp-lab
    teams.leave(db, user=bob)
    other = teams.create_team(db, user=carol, name="pick-lab", display_name="Pick Lab")
    invitation = teams.invite(db, admin=carol, team=other, username="bob")
    teams.accept(db, user=bob, invitation_id=invitation.id)
    db.commit()
    _done(db, bob, challenge, [True, False])  # made in pick-lab
    assert _rows(client) == [("grasp-lab", "bob", 1.0), ("pick-lab", "bob", 0.5)]
    assert teams.leave(db, user=alice) is None  # the last member: grasp-lab dissolves
    db.commit()
    # Its submission is bob's own now, but bob is in pick-lab: no row of his own.
    assert _rows(client) == [("pick-lab", "bob", 0.5)]
    teams.leave(db, user=bob)
    db.commit()
    assert _rows(client) == [(None, "bob", 1.0), ("pick-lab", "bob", 0.5)]


def test_per_user_mode_is_unaffected_and_switching_rebuilds(
    client: TestClient, db: Session
) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    _join(db, alice, bob)
    _done(db, alice, challenge, [True, False])
    _done(db, bob, challenge, [True, True])
    assert _rows(client) == [(None, "bob", 1.0), (None, "alice", 0.5)]
    set_team_mode(db, slug="server-tiny", on=True)
    db.commit()
    assert _rows(client) == [("grasp-lab", "bob", 1.0)]
    set_team_mode(db, slug="server-tiny", on=False)
    db.commit()
    assert _rows(client) == [(None, "bob", 1.0), (None, "alice", 0.5)]


def test_the_board_shows_method_paper_and_code(client: TestClient, db: Session) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20)
    _done(
        db,
        make_user(db, "alice"),
        challenge,
        [True, True],
        method="=Diffusion Policy",
        paper_url="https://arxiv.org/abs/2303.04137",
        code_url="https://github.com/real-stanford/diffusion_policy",
    )
    _done(db, make_user(db, "bob"), challenge, [True, False])
    board = client.get(BOARD).json()
    first, second = board["items"]
    assert (first["method"], first["paper_url"], first["code_url"]) == (
        "=Diffusion Policy",
        "https://arxiv.org/abs/2303.04137",
        "https://github.com/real-stanford/diffusion_policy",
    )
    assert (second["method"], second["paper_url"], second["code_url"]) == (None, None, None)

    header, *rows = csv.reader(io.StringIO(client.get(BOARD + "&format=csv").text))
    assert rows[0][header.index("method")] == "'=Diffusion Policy"  # no spreadsheet formula
    assert rows[0][header.index("code_url")] == "https://github.com/real-stanford/diffusion_policy"
    assert rows[1][header.index("method")] == ""

    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert (
        '<a href="https://arxiv.org/abs/2303.04137" rel="noopener nofollow" '
        'title="The method\'s paper">=Diffusion Policy</a>'
    ) in html
    assert (
        '<a class="code-link" href="https://github.com/real-stanford/diffusion_policy" '
        'rel="noopener nofollow"'
    ) in html

    console = stdout()
    with console.capture() as captured:
        console.print(leaderboard_table(board))
    assert "method" in captured.get()
    assert "=Diffusion Policy" in captured.get()


def test_an_edited_method_reaches_the_board(client: TestClient, db: Session) -> None:
    from server.submissions.method import Method
    from server.submissions.service import edit

    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20)
    alice = make_user(db, "alice")
    s = _done(db, alice, challenge, [True, True])
    edit(db, user=alice, submission=s, method=Method(name="ACT", paper_url="https://x.org/p"))
    db.commit()
    (row,) = client.get(BOARD).json()["items"]
    assert (row["method"], row["paper_url"]) == ("ACT", "https://x.org/p")


def test_the_terminal_board_has_no_method_column_when_no_row_names_one(
    client: TestClient, db: Session
) -> None:
    challenge = make_challenge(db, quota_per_day=20, quota_concurrent=20)
    _done(db, make_user(db, "alice"), challenge, [True, True])
    table = leaderboard_table(client.get(BOARD).json())
    assert "method" not in [c.header for c in table.columns]
