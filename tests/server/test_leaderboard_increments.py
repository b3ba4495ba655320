"""A snapshot brought up to date by the entries that came and went equals the board read
whole, after any change: new best rows, replaced and removed ones, baselines, teams formed,
left and dissolved. On Postgres the snapshot is advanced; on SQLite, whose ids are reused, it
is read whole every time."""

from __future__ import annotations

import csv
import io
import random
from typing import Any

import pytest
from sqlalchemy.orm import Session

from server.kit.spreadsheets import csv_safe
from server.leaderboard import ties
from server.leaderboard.pages import sort_value
from server.leaderboard.schemas import LeaderboardRowOut
from server.leaderboard.service import phase_versions
from server.leaderboard.snapshot import Snapshot, Snapshots, advance, read_whole
from server.models import Challenge, State, Submission, User, team_of
from server.standings.entries import refresh
from server.submissions.reports import report_final, report_state
from server.teams import service as teams
from testkit.factories import make_challenge, make_user, queue_submission, result_doc

SLUG, PHASE = "server-tiny", "dev"


def _finish(
    db: Session, rng: random.Random, user: User, challenge: Challenge, method: str | None = None
) -> None:
    s = queue_submission(db, user, challenge)
    s.method = method
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    # Four episodes: five possible scores, so equal scores (and ties) are common.
    outcome = result_doc([rng.random() < 0.5 for _ in range(4)])
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=outcome)


def _flip(db: Session, rng: random.Random, what: str) -> None:
    """Hide or show, or flag or unflag as a baseline, a random finished submission."""
    done = db.query(Submission).filter(Submission.state == State.SUCCEEDED).all()
    if not done:
        return
    s = rng.choice(done)
    setattr(s, what, not getattr(s, what))
    db.flush()
    refresh(db, phase_id=s.phase_id, user_id=s.user_id)


def _team_change(db: Session, rng: random.Random, users: list[User]) -> None:
    """A random user leaves their team (maybe dissolving it), or forms one with another."""
    user = rng.choice(users)
    if team_of(db, user_id=user.id) is not None:
        teams.leave(db, user=user)
        return
    other = rng.choice([u for u in users if u is not user])
    if team_of(db, user_id=other.id) is not None:
        return
    n = rng.randrange(10**6)
    team = teams.create_team(db, user=user, name=f"team-{n}", display_name=f"Team {n}")
    invitation = teams.invite(db, admin=user, team=team, username=other.username)
    teams.accept(db, user=other, invitation_id=invitation.id)


def _change(db: Session, rng: random.Random, users: list[User], challenge: Challenge) -> None:
    roll = rng.random()
    if roll < 0.55:
        _finish(db, rng, rng.choice(users), challenge)
    elif roll < 0.7:
        _flip(db, rng, "hidden")
    elif roll < 0.8:
        _flip(db, rng, "baseline")
    elif challenge.team_mode:
        _team_change(db, rng, users)
    else:
        _flip(db, rng, "public")
    db.commit()


SORTS = [
    (key, way, limit) for key in ("user", "score") for way in (True, False) for limit in (3, 50)
]


def _sorted(board: Snapshot) -> list[list[int]]:
    return [board.order(sort_value(key), key, way, limit) for key, way, limit in SORTS]


def assert_same(got: Snapshot, whole: Snapshot) -> None:
    """Both boards show the same rows, ranks and ties, in every page size, format and sorted
    view (a sorted view of the first rows may be the last snapshot's)."""
    assert _sorted(got) == _sorted(whole)
    assert [s.id for s in got.rows] == [s.id for s in whole.rows]
    assert (got.ranks, got.groups, got.tied) == (whole.ranks, whole.groups, whole.tied)
    assert [got.row(i) for i in range(got.total)] == [whole.row(i) for i in range(whole.total)]
    for per_page in (1, 3, 50):
        for page in range(1, got.total // per_page + 2):
            for format in ("json", "csv"):
                assert got.body(page, per_page, format) == whole.body(page, per_page, format)


@pytest.mark.parametrize("team_mode", [False, True])
def test_an_advanced_snapshot_equals_the_board_read_whole(db: Session, team_mode: bool) -> None:
    rng = random.Random(1234 + team_mode)
    challenge = make_challenge(db, quota_per_day=500, quota_concurrent=500, teams=team_mode)
    users = [make_user(db, f"user{i}") for i in range(8)]
    for user in users[:4]:
        _finish(db, rng, user, challenge)
    db.commit()
    phase_id, version, _ = phase_versions(db, slug=SLUG, phase=PHASE)
    held = read_whole(
        db, slug=SLUG, phase=PHASE, phase_id=phase_id, version=version, board_version=1
    )
    stable = db.get_bind().dialect.name == "postgresql"
    advanced = 0
    for _ in range(40):
        _change(db, rng, users, challenge)
        phase_id, version, _ = phase_versions(db, slug=SLUG, phase=PHASE)
        whole = read_whole(
            db, slug=SLUG, phase=PHASE, phase_id=phase_id, version=version, board_version=1
        )
        _sorted(held)  # kept, to be carried over where the rows sorted are the same
        moved = advance(db, held, version=version)
        if moved is not None:
            advanced += 1
            kept = set(held.by_id) & set(moved.by_id)
            assert all(moved.by_id[i] is held.by_id[i] for i in kept)  # derived once
            assert_same(moved, whole)
        held = moved or whole
    assert advanced == (40 if stable else 0)
    assert held.total > 4


def test_snapshots_follow_a_changing_board(db: Session) -> None:
    rng = random.Random(99)
    challenge = make_challenge(db, quota_per_day=500, quota_concurrent=500, teams=True)
    users = [make_user(db, f"user{i}") for i in range(6)]
    boards = Snapshots(max_age=0.0)
    for _ in range(25):
        _change(db, rng, users, challenge)
        got = boards.current_in(db, slug=SLUG, phase=PHASE)
        phase_id, version, _ = phase_versions(db, slug=SLUG, phase=PHASE)
        assert got.version == version
        assert_same(
            got,
            read_whole(
                db, slug=SLUG, phase=PHASE, phase_id=phase_id, version=version, board_version=1
            ),
        )


def test_a_rows_json_and_csv_line_are_the_whole_rows(db: Session) -> None:
    rng = random.Random(5)
    challenge = make_challenge(db, quota_per_day=500, quota_concurrent=500)
    users = [make_user(db, name) for name in ("ada", "bob", "cyd", "eve")]
    for n in range(3):
        for user in users:
            _finish(db, rng, user, challenge, method=[None, '=1+1, "a"', "plain"][n])
    _flip(db, rng, "baseline")
    db.commit()
    phase_id, version, _ = phase_versions(db, slug=SLUG, phase=PHASE)
    board = read_whole(
        db, slug=SLUG, phase=PHASE, phase_id=phase_id, version=version, board_version=1
    )
    assert any(board.tied)
    assert None in board.ranks
    lines = list(csv.reader(io.StringIO(board.body(1, 50, "csv").decode())))
    assert len(lines) == board.total + 1
    for i in range(board.total):
        row = board.row(i)
        single = board.body(i + 1, 1, "json").decode()
        expected = LeaderboardRowOut(**row.__dict__).model_dump_json()
        assert f'"items":[{expected}]' in single
        cells = lines[i + 1]
        assert len(cells) == len(lines[0])
        assert cells[:2] == ["" if row.rank is None else str(row.rank), csv_safe(row.username)]
        assert cells[6:8] == [str(row.tied), "" if row.tie_group is None else str(row.tie_group)]
        assert cells[9] == str(row.submission_id)
        assert cells[12] == csv_safe(row.method or "")


def _finished(db: Session, user: User, challenge: Challenge, successes: list[bool]) -> None:
    s = queue_submission(db, user, challenge)
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=result_doc(successes))
    db.commit()


def test_a_row_added_below_regroups_the_rows_above_and_tests_only_the_new_pair(
    db: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    challenge = make_challenge(db, quota_per_day=50, quota_concurrent=50)
    # alice 16 and bob 10 of 20, bob's within alice's: p = 2/64 = 0.031, two groups at 0.05.
    _finished(db, make_user(db, "alice"), challenge, [i < 16 for i in range(20)])
    _finished(db, make_user(db, "bob"), challenge, [i < 10 for i in range(20)])
    phase_id, version, _ = phase_versions(db, slug=SLUG, phase=PHASE)
    held = read_whole(
        db, slug=SLUG, phase=PHASE, phase_id=phase_id, version=version, board_version=1
    )
    assert held.groups == [1, 2]

    tested: list[tuple[str, str]] = []
    real = ties.paired_p_value

    def counted(db: Session, above: Any, below: Any) -> float:
        tested.append((above.username, below.username))
        return real(db, above, below)

    monkeypatch.setattr(ties, "paired_p_value", counted)
    # carol below bob (bob alone 8, carol alone 1: p = 0.039): the last row is the only one
    # that changed, yet Holm's thresholds over two comparisons leave no boundary above it.
    _finished(db, make_user(db, "carol"), challenge, [i in (0, 1, 16) for i in range(20)])
    phase_id, version, _ = phase_versions(db, slug=SLUG, phase=PHASE)
    moved = advance(db, held, version=version)
    tested_by_advance = list(tested)
    whole = read_whole(
        db, slug=SLUG, phase=PHASE, phase_id=phase_id, version=version, board_version=1
    )
    if db.get_bind().dialect.name == "postgresql":
        assert moved is not None
        assert tested_by_advance == [("bob", "carol")]  # alice against bob was kept
        assert_same(moved, whole)
    assert whole.groups == [1, 1, 1]
    assert whole.tied == [False, True, True]
