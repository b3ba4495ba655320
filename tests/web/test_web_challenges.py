"""Home, challenge and leaderboard pages: what they show, sorting, and the score history."""

from __future__ import annotations

import re
from datetime import UTC, datetime, timedelta
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server.challenges.service import ChallengeOptions, load_challenge
from server.leaderboard.challenge_page import ScoreHistory
from server.leaderboard.service import record_points
from server.models import Challenge, Phase
from server.standings.entries import refresh
from server.teams.service import create_team
from testkit.factories import SUITE, make_challenge, make_user
from testkit.verification import suite_copy, write_report
from tests.web.helpers import browser, finished


def board_users(html: str) -> list[str]:
    """Participants in the order the leaderboard table lists them."""
    body = html.split('id="board"')[1]
    return re.findall(r'<a href="/submissions/\d+">([^<]+)</a>', body)


def test_home_lists_open_challenges_first(client: TestClient, db: Session) -> None:
    past = datetime.now(UTC) - timedelta(days=1)
    make_challenge(db, closes={"dev": past, "test": past}, opens={"dev": past - timedelta(days=9)})
    closed = client.get("/").text
    assert "No challenge is open for submissions right now." in closed
    assert "Closed or not yet open" in closed
    make_challenge(db, closes={"dev": past + timedelta(days=9)})  # dev reopens
    html = client.get("/").text
    assert 'href="/challenges/server-tiny"' in html.split("Closed or not yet open")[0]


def test_challenge_page_shows_rules_phases_commitment_quota_and_board(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    alice = make_user(db, "alice")
    finished(db, alice, tiny, [True, False])
    test_phase = next(p for p in tiny.phases if p.name == "test")
    html = browser(client, "alice").get("/challenges/server-tiny").text
    assert "PickCube-v1" in html
    assert "obs_noise" in html
    assert "sigma 0.01" in html
    assert test_phase.seed_commitment in html
    assert "3 submissions per rolling 24 hours" in html
    assert "Your quota: 1 of 3 used" in html
    assert board_users(html.replace('id="top"', 'id="board"')) == ["alice"]
    assert "Best score over time" in html
    assert 'class="step"' in html
    assert "This challenge counts per participant, not per team" in html
    anonymous = client.get("/challenges/server-tiny").text
    assert "Your quota" not in anonymous
    assert client.get("/challenges/nope").status_code == 404
    assert client.get("/challenges/server-tiny?phase=nope").status_code == 404


def test_leaderboard_has_intervals_stress_columns_baselines_and_downloads(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    alice, bob, admin = make_user(db, "alice"), make_user(db, "bob"), make_user(db, "root1")
    finished(db, alice, tiny, [True, True, False, False])
    finished(db, bob, tiny, [True, True, True, False])
    base = finished(db, admin, tiny, [True, False, False, False])
    judge = browser(client, "root1")
    html = judge.get(f"/submissions/{base.id}").text
    assert "Flag as baseline" not in html  # not an admin
    base.baseline = True
    db.flush()
    refresh(db, phase_id=base.phase_id, user_id=base.user_id)
    db.commit()
    page = client.get("/challenges/server-tiny/leaderboard?phase=dev")
    assert page.status_code == 200
    html = page.text
    assert board_users(html) == ["bob", "alice", "root1"]
    assert html.count('class="ibar"') == 3
    assert "95% interval </span>" in html  # the interval's text, not only its bar
    assert ">obs_<wbr>noise<" in html  # the stress condition's column, breakable
    assert '<span class="badge">baseline</span>' in html
    assert "format=csv" in html
    assert "format=json" in html
    csv = client.get("/api/v1/challenges/server-tiny/leaderboard?phase=dev&format=csv")
    assert csv.status_code == 200
    assert "bob" in csv.text


def test_leaderboard_sorts_by_any_column_both_ways(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    for name, successes in (("carol", [True, False]), ("alice", [True, True]), ("bob", [False])):
        finished(db, make_user(db, name), tiny, successes)
    url = "/challenges/server-tiny/leaderboard?phase=dev"
    assert board_users(client.get(url).text) == ["alice", "carol", "bob"]
    assert board_users(client.get(f"{url}&sort=user").text) == ["alice", "bob", "carol"]
    assert board_users(client.get(f"{url}&sort=user&dir=desc").text) == ["carol", "bob", "alice"]
    by_task = client.get(f"{url}&sort=task:PickCube-v1&dir=asc").text
    assert board_users(by_task) == ["bob", "carol", "alice"]
    assert 'aria-sort="ascending"' in by_task
    assert board_users(client.get(f"{url}&sort=nonsense").text) == ["alice", "carol", "bob"]
    sideways = client.get(f"{url}&dir=sideways")
    assert sideways.status_code == 422
    assert "<strong>dir</strong>: must be one of: asc, desc" in sideways.text  # not a pattern


def test_score_history_keeps_only_records_and_follows_the_board_version(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    dev: Phase = next(p for p in tiny.phases if p.name == "dev")
    history = ScoreHistory()
    assert history.chart(db, dev) is None
    first = finished(db, make_user(db, "alice"), tiny, [True, False])
    finished(db, make_user(db, "bob"), tiny, [False, False])
    best = finished(db, make_user(db, "carol"), tiny, [True, True])
    finished(db, make_user(db, "dave"), tiny, [True, True])  # a tie is not a record
    db.refresh(dev)
    points = record_points(db, phase_id=dev.id)
    assert [p.submission_id for p in points] == [first.id, best.id]
    chart = history.chart(db, dev)
    assert chart is not None
    assert len(chart.markers) == 2
    assert history.chart(db, dev) is chart  # same version: cached


def test_the_demos_visual_challenge_page_says_what_it_runs_and_what_a_policy_sees(
    client: TestClient, db: Session
) -> None:
    from manieval.demo import TRACKS, VISUAL, challenge_options

    for track in TRACKS:  # as the demo loads them: the visual one is a track of the core one
        load_challenge(db, track.challenge, challenge_options(track, 2), seed_secret="s" * 32)
    db.commit()
    html = client.get(f"/challenges/{VISUAL.challenge}").text
    assert "Leaderboard, track state, phase dev" in html  # the other track's board
    assert "In this demo</strong> the visual track runs small" in html
    tasks = html.split('id="tasks-heading"')[1].split("</section>")[0]
    assert re.findall(r'<th scope="row">([^<]+)</th>', tasks) == ["PickCube-v1", "PushCube-v1"]
    assert '<td class="numeric">1</td>' in tasks  # one episode each
    assert "Pick up the red cube and hold it still at the goal position." in tasks
    rules = html.split('id="rules-heading"')[1].split("</section>")[0]
    assert "<strong>nominal</strong> (nominal)." in rules  # the only condition it runs
    assert "<code>sensor_data/*/rgb</code>" in rules
    assert "<code>extra/tcp_pose</code>" in rules


def test_a_team_mode_challenge_says_it_counts_per_team_and_whose_quota_is_shown(
    client: TestClient, db: Session
) -> None:
    make_challenge(db, quota_per_day=3, quota_concurrent=2, teams=True)
    alice = make_user(db, "alice")
    create_team(db, user=alice, name="grasp-lab", display_name="Grasp Lab")
    db.commit()
    html = browser(client, "alice").get("/challenges/server-tiny").text
    assert "This challenge counts per team: a team's members share the quota above" in html
    assert "Your team's quota (grasp-lab): 0 of 3 used" in html


def test_challenge_page_and_api_show_the_verification_report(
    client: TestClient, db: Session, tmp_path: Path
) -> None:
    suite = suite_copy(tmp_path, SUITE)
    write_report(suite)
    load_challenge(db, suite, ChallengeOptions(verified_only=True), seed_secret="s" * 32)
    db.commit()
    html = client.get("/challenges/server-tiny").text
    section = html.split('id="verification-heading"')[1].split("</section>")[0]
    assert '<span class="badge badge-open">verified</span>' in section
    assert "local:scripted" in section
    assert '<th scope="row">PickCube-v1</th>' in section
    assert "9 of 10 (at least 50%)" in section
    assert "0 of 10 (under 20%)" in section
    assert "identical" in section
    api = client.get("/api/v1/challenges/server-tiny").json()["verification"]
    assert api["passed"] is True
    assert api["problems"] == []
    assert api["report"]["tasks"][0]["reference_successes"] == 9


def test_challenge_page_says_a_challenge_loaded_unverified_is_not_verified(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    html = client.get("/challenges/server-tiny").text
    section = html.split('id="verification-heading"')[1].split("</section>")[0]
    assert "not verified" in section
    assert "no verification report beside the suite" in section
    listed = section.split('class="verification-problems"')[1].split("</ul>")[0]
    assert "/" not in re.sub(r"<[^>]*>", "", listed)  # no server path on a public page
    api = client.get("/api/v1/challenges/server-tiny").json()["verification"]
    assert api["passed"] is False
    assert api["report"] is None
