"""Every board in the suite's order (web, JSON, CSV), statistical ties marked on the web and in
the API, challenge titles and descriptions as written."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from evaluator.results import ConditionResult, aggregate_task
from server.challenges.service import ChallengeOptions, display_title, load_challenge
from server.models import Challenge, State
from server.submissions.reports import report_final, report_state
from testkit.factories import SUITE, make_challenge, make_user, queue_submission, result_doc
from tests.web.helpers import finished

# Tasks and conditions deliberately out of alphabetical order.
TASKS = ("PushCube-v1", "PickCube-v1")
CONDITIONS = ("nominal", "obs_noise", "action_delay")
BOARD = "/api/v1/challenges/{slug}/leaderboard?phase=dev"


@pytest.fixture
def unsorted(db: Session, tmp_path: Path) -> Challenge:
    suite = tmp_path / "unsorted.yaml"
    suite.write_text(
        SUITE.read_text()
        .replace("name: server-tiny", "name: unsorted")
        .replace(
            "  - {env_id: PickCube-v1, max_episode_steps: 12, episodes: 2}\n",
            "".join(f"  - {{env_id: {t}, max_episode_steps: 12, episodes: 2}}\n" for t in TASKS),
        )
        .replace(
            "  - {name: obs_noise, params: {kind: obs_noise, sigma: 0.01}}\n",
            "  - {name: obs_noise, params: {kind: obs_noise, sigma: 0.01}}\n"
            "  - {name: action_delay, params: {kind: action_delay, steps: 1}}\n",
        )
    )
    challenge = load_challenge(db, suite, ChallengeOptions(), seed_secret="s" * 32)
    db.commit()
    return challenge


def _finish_unsorted(db: Session, challenge: Challenge, username: str) -> None:
    doc = result_doc([True, False])
    episodes = doc.conditions[0].tasks[0].episodes
    # Reported in alphabetical order, as a worker might: the board must not follow it.
    conditions = [
        ConditionResult(
            name=name,
            params={"kind": name},
            score=0.5,
            tasks=[aggregate_task(t, 2, list(episodes)) for t in sorted(TASKS)],
        )
        for name in sorted(CONDITIONS)
    ]
    doc = doc.model_copy(update={"conditions": conditions})
    s = queue_submission(db, make_user(db, username), challenge)
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=doc)
    db.commit()


def test_json_csv_and_web_boards_list_tasks_and_conditions_in_the_suites_order(
    client: TestClient, db: Session, unsorted: Challenge
) -> None:
    _finish_unsorted(db, unsorted, "alice")
    body = client.get(BOARD.format(slug="unsorted")).json()
    assert body["tasks"] == list(TASKS)
    assert body["conditions"] == list(CONDITIONS)
    (row,) = body["items"]
    assert list(row["tasks"]) == list(TASKS)
    assert list(row["conditions"]) == list(CONDITIONS)

    text = client.get(BOARD.format(slug="unsorted") + "&format=csv").text
    header = next(csv.reader(io.StringIO(text)))
    assert [h for h in header if h.endswith(" success")] == [f"{t} success" for t in TASKS]
    assert [h for h in header if h.startswith("condition ")] == [
        f"condition {c}" for c in CONDITIONS
    ]

    html = client.get("/challenges/unsorted/leaderboard?phase=dev").text
    head = html.split("<thead>")[1].split("</thead>")[0]
    assert head.index("Push<wbr>Cube-v1") < head.index("Pick<wbr>Cube-v1")
    assert head.index("obs_<wbr>noise") < head.index("action_<wbr>delay")


def test_rows_whose_score_intervals_overlap_the_row_above_are_tied(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    finished(db, make_user(db, "alice"), tiny, [True] * 10)  # 10/10: [0.72, 1]
    finished(db, make_user(db, "bob"), tiny, [True] * 9 + [False])  # 9/10: [0.60, 0.98]
    finished(db, make_user(db, "carol"), tiny, [False] * 10)  # 0/10: [0, 0.28]
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    assert [(r["username"], r["rank"], r["tied"]) for r in items] == [
        ("alice", 1, False),
        ("bob", 2, True),
        ("carol", 3, False),
    ]
    assert items[0]["score_ci_low"] == pytest.approx(0.7225, abs=1e-4)
    assert items[0]["score_ci_high"] == pytest.approx(1.0)
    # A page boundary does not hide the row above.
    second = client.get(BOARD.format(slug="server-tiny") + "&per_page=1&page=2").json()
    assert [(r["username"], r["tied"]) for r in second["items"]] == [("bob", True)]
    header, *rows = csv.reader(
        io.StringIO(client.get(BOARD.format(slug="server-tiny") + "&format=csv").text)
    )
    assert header[:7] == [
        "rank",
        "username",
        "baseline",
        "score",
        "score_ci_low",
        "score_ci_high",
        "tied",
    ]
    assert [(r[0], r[1], r[6]) for r in rows] == [
        ("1", "alice", "False"),
        ("2", "bob", "True"),
        ("3", "carol", "False"),
    ]

    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert html.count('class="badge badge-tie"') == 1 + 1  # bob's, and the legend's
    assert 'title="Statistically tied with rank 1' in html
    assert "72\u2013100%" in html  # alice's score interval (an en dash) under her score


def test_a_baseline_between_two_rows_does_not_break_their_tie(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    from server.standings.entries import refresh

    finished(db, make_user(db, "alice"), tiny, [True] * 10)
    base = finished(db, make_user(db, "root1"), tiny, [True] * 10)
    base.baseline = True
    db.flush()
    refresh(db, phase_id=base.phase_id, user_id=base.user_id)
    db.commit()
    finished(db, make_user(db, "bob"), tiny, [True] * 9 + [False])
    items = client.get(BOARD.format(slug="server-tiny") + "&per_page=1&page=3").json()["items"]
    assert [(r["username"], r["rank"], r["tied"]) for r in items] == [("bob", 2, True)]


def test_titles_keep_brand_casing_and_a_declared_title_wins() -> None:
    assert display_title("maniskill-core") == "ManiSkill Core"
    assert display_title("server_tiny") == "Server Tiny"
    assert display_title("maniskill3-rgbd-v2") == "ManiSkill3 RGBD V2"
    assert display_title("maniskill-core", "ManiSkill 3: the core tasks") == (
        "ManiSkill 3: the core tasks"
    )


def test_descriptions_render_as_markdown_and_never_as_raw_html(
    client: TestClient, db: Session
) -> None:
    description = (
        "Run `manieval evaluate` first.\n\n"
        "<script>alert(1)</script> [docs](https://example.org/d) [bad](javascript:alert(1))"
    )
    make_challenge(db, description=description)
    html = client.get("/challenges/server-tiny").text
    assert "<code>manieval evaluate</code>" in html
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in html
    assert "<script>alert" not in html
    assert '<a href="https://example.org/d" rel="nofollow noopener">docs</a>' in html
    assert 'href="javascript:' not in html
    assert "Public seeds." in html  # the phases' descriptions, inline
    home = client.get("/").text
    assert "<code>manieval evaluate</code>" in home  # the card's first paragraph
    assert "alert" not in home


def test_rows_stored_before_score_intervals_are_measured_again(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    from sqlalchemy import select

    from server.models import LeaderboardEntry

    finished(db, make_user(db, "alice"), tiny, [True] * 10)
    finished(db, make_user(db, "bob"), tiny, [True] * 9 + [False])
    for entry in db.scalars(select(LeaderboardEntry)):
        entry.summary = {k: v for k, v in entry.summary.items() if k != "score_interval"}
    db.commit()
    db.expire_all()
    assert all("score_interval" not in e.summary for e in db.scalars(select(LeaderboardEntry)))
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    assert [(r["username"], r["tied"]) for r in items] == [("alice", False), ("bob", True)]
    assert items[1]["score_ci_low"] == pytest.approx(0.5958, abs=1e-4)
