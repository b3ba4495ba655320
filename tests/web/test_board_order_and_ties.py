"""Every board in the suite's order (web, JSON, CSV), statistical ties marked on the web and in
the API, challenge titles and descriptions as written."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

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


def paired(both: int, only_a: int, only_b: int, neither: int) -> tuple[list[bool], list[bool]]:
    """Two runs over the same episodes (seeds) with this 2x2 table of outcomes."""
    a = [True] * (both + only_a) + [False] * (only_b + neither)
    b = [True] * both + [False] * only_a + [True] * only_b + [False] * neither
    return a, b


def _board(client: TestClient) -> tuple[list[dict[str, Any]], list[list[str]], str]:
    """The board as the API's JSON, the CSV's rows (header first) and the web page."""
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    text = client.get(BOARD.format(slug="server-tiny") + "&format=csv").text
    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    return items, list(csv.reader(io.StringIO(text))), html


def _overlap(upper: dict[str, Any], lower: dict[str, Any]) -> bool:
    return lower["score_ci_high"] >= upper["score_ci_low"]


def test_overlapping_intervals_that_the_paired_test_separates_are_two_groups(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    # B solves every episode A solves and 15 more of the 100: 65 against 50.
    worse, better = paired(both=50, only_a=0, only_b=15, neither=35)
    finished(db, make_user(db, "alice"), tiny, better)
    finished(db, make_user(db, "bob"), tiny, worse)
    items, rows, html = _board(client)
    assert _overlap(*items)  # the old rule called them tied
    assert [(r["username"], r["rank"], r["tied"], r["tie_group"]) for r in items] == [
        ("alice", 1, False, 1),
        ("bob", 2, False, 2),
    ]
    assert rows[0][6:8] == ["tied", "tie_group"]
    assert [(r[1], r[6], r[7]) for r in rows[1:]] == [
        ("alice", "False", "1"),
        ("bob", "False", "2"),
    ]
    assert '<span aria-hidden="true">G2</span><span class="visually-hidden">tie group 2:' in html
    assert 'title="Tie group 1: the first group"' in html
    assert "the paired test on their shared episodes separates it from rank 1" in html
    assert 'href="/help/metrics#paired-significance"' in html


def test_separate_intervals_that_the_paired_test_does_not_separate_share_a_group(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    # 58 against 38 of 100, on 96 discordant episodes of which B wins 38: p = 0.052.
    better, worse = paired(both=0, only_a=58, only_b=38, neither=4)
    finished(db, make_user(db, "alice"), tiny, better)
    finished(db, make_user(db, "bob"), tiny, worse)
    items, rows, html = _board(client)
    assert not _overlap(*items)  # the old rule set them apart
    assert [(r["username"], r["tied"], r["tie_group"]) for r in items] == [
        ("alice", False, 1),
        ("bob", True, 1),
    ]
    assert [(r[1], r[6], r[7]) for r in rows[1:]] == [("alice", "False", "1"), ("bob", "True", "1")]
    assert html.count('<span aria-hidden="true">G1</span>') == 2
    assert "tie group 1, not significantly different from rank 1" in html
    assert (
        'title="Tie group 1: the paired test on their shared episodes does not separate it' in html
    )
    # A page boundary does not hide the row above.
    second = client.get(BOARD.format(slug="server-tiny") + "&per_page=1&page=2").json()
    assert [(r["username"], r["tied"], r["tie_group"]) for r in second["items"]] == [
        ("bob", True, 1)
    ]


def test_holm_corrects_over_the_boards_comparisons_at_the_phases_level(
    client: TestClient, db: Session, tiny: Challenge, tmp_path: Path
) -> None:
    # Alone, 16 against 10 of 20 (6 discordant, all A's) is p = 0.031: two groups at 0.05.
    finished(db, make_user(db, "alice"), tiny, [i < 16 for i in range(20)])
    finished(db, make_user(db, "bob"), tiny, [i < 10 for i in range(20)])
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    assert [r["tie_group"] for r in items] == [1, 2]
    # A third below bob (bob alone 8, carol alone 1: p = 0.039) makes two comparisons, and
    # Holm asks the smaller p-value to pass 0.025: no boundary is left.
    finished(db, make_user(db, "carol"), tiny, [i in (0, 1, 16) for i in range(20)])
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    assert [(r["username"], r["tie_group"]) for r in items] == [
        ("alice", 1),
        ("bob", 1),
        ("carol", 1),
    ]
    # The organizer's level, from the suite: at 0.1, both boundaries stand.
    looser = tmp_path / "server-tiny.yaml"
    looser.write_text(
        SUITE.read_text().replace(
            "seeds: {kind: public, start: 0}}",
            "seeds: {kind: public, start: 0}, significance_level: 0.1}",
        )
    )
    load_challenge(db, looser, ChallengeOptions(), seed_secret="s" * 32)
    db.commit()
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    assert [r["tie_group"] for r in items] == [1, 2, 3]
    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert "(Holm, at 0.1)" in html


def test_a_challenge_page_shows_the_tie_groups_of_its_top_rows(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    worse, better = paired(both=50, only_a=0, only_b=15, neither=35)
    finished(db, make_user(db, "alice"), tiny, better)
    finished(db, make_user(db, "bob"), tiny, worse)
    html = client.get("/challenges/server-tiny").text
    assert '<span aria-hidden="true">G1</span>' in html
    assert '<span aria-hidden="true">G2</span>' in html


def test_the_help_page_serves_the_metrics_doc_with_its_anchors(client: TestClient) -> None:
    html = client.get("/help/metrics").text
    assert '<h2 id="paired-significance">Paired significance</h2>' in html
    assert '<h3 id="tie-groups-and-the-correction">' in html
    assert "<table>" in html


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


def test_rows_stored_before_their_outcomes_are_paired_from_their_episodes(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    from sqlalchemy import select

    from server.models import LeaderboardEntry

    worse, better = paired(both=50, only_a=0, only_b=15, neither=35)
    finished(db, make_user(db, "alice"), tiny, better)
    finished(db, make_user(db, "bob"), tiny, worse)
    for entry in db.scalars(select(LeaderboardEntry)):
        assert entry.outcomes is not None
        entry.outcomes = None
    db.commit()
    items = client.get(BOARD.format(slug="server-tiny")).json()["items"]
    assert [(r["username"], r["tie_group"]) for r in items] == [("alice", 1), ("bob", 2)]
