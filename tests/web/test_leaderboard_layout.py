"""The leaderboard of the widest bundled suite (maniskill-core: six tasks, three stress
conditions) in Chromium: every column heading inside the table's box at 1,280 px, nothing
hidden; statistical ties marked; on a phone, sticky rank and participant with a scroll cue.

Widths are measured with each heading's bounding box against the scroll container's, not timed.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from evaluator.results import (
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    SuiteRef,
    Versions,
    aggregate_task,
)
from evaluator.suite import load_suite
from server.app import create_app
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from server.models import Challenge, State
from server.standings.entries import refresh
from server.submissions.reports import report_final, report_state
from testkit.factories import RecordingQueue, make_user, queue_submission
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium, serving

SUITE = load_suite("maniskill-core")
TASKS = [t.env_id for t in SUITE.tasks]
CONDITIONS = [c.name for c in SUITE.conditions]
EPISODES = 3  # per task: small samples, wide intervals, as on a try-out board


def core_result(successes: int) -> EvaluationResult:
    """A completed maniskill-core result: `successes` of EPISODES on every task, one fewer
    under each stress condition."""
    conditions = []
    for n, name in enumerate(CONDITIONS):
        won = max(0, successes - (1 if n else 0))
        tasks = [
            aggregate_task(
                env_id,
                EPISODES,
                [
                    EpisodeResult(
                        index=i,
                        seed=i,
                        success_once=i < won,
                        success_at_end=None,
                        steps=10,
                        episode_return=0.0,
                        wall_time_s=0.1,
                    )
                    for i in range(EPISODES)
                ],
            )
            for env_id in TASKS
        ]
        score = sum(t.success_rate for t in tasks) / len(tasks)
        conditions.append(
            ConditionResult(name=name, params={"kind": name}, score=score, tasks=tasks)
        )
    now = datetime.now(UTC)
    return EvaluationResult(
        suite=SuiteRef(name=SUITE.name, version=SUITE.version, sha256=SUITE.sha256()),
        phase="dev",
        policy="test",
        versions=Versions(manieval="0", mani_skill="0", sapien="0", torch="0", python="3"),
        started_at=now,
        finished_at=now,
        status="completed",
        score=conditions[0].score,
        conditions=conditions,
    )


# Long names on purpose: the participant column must wrap them, not widen the table.
PARTICIPANTS = (
    ("a-rather-long-username-01", EPISODES, False),
    ("second-participant-name", EPISODES, False),  # the same episodes: the first's group
    ("demo", EPISODES - 1, True),  # a baseline: the widest rank cell, and no rank
    ("third", 0, False),  # lost every episode the second won: a group of its own
)


@dataclass(frozen=True)
class Board:
    url: str
    challenge: str


@pytest.fixture
def board(tmp_path: Path) -> Iterator[Board]:
    settings = Settings(dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False)
    settings.data_dir.mkdir(parents=True)
    upgrade(settings.resolved_database_url)
    sessions: sessionmaker[Session] = session_factory(make_engine(settings.resolved_database_url))
    with sessions() as db:
        challenge = load_challenge(
            db, "maniskill-core", ChallengeOptions(), seed_secret=settings.secret("seed_secret")
        )
        db.commit()
        for username, successes, baseline in PARTICIPANTS:
            _finish(db, username, challenge, successes, baseline=baseline)
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield Board(url=url, challenge=challenge.slug)


def _finish(
    db: Session, username: str, challenge: Challenge, successes: int, *, baseline: bool
) -> None:
    submission = queue_submission(db, make_user(db, username), challenge)
    assert report_state(db, submission.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, submission.id, 1, State.RUNNING, "evaluating")
    assert report_final(
        db, submission.id, 1, State.SUCCEEDED, "done", result=core_result(successes)
    )
    if baseline:
        submission.baseline = True
        db.flush()
        refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    db.commit()


# The table's geometry: its scroll box, and each heading's box and text.
MEASURE = """() => {
  const scroller = document.querySelector('#board').closest('.table-scroll');
  const box = scroller.getBoundingClientRect();
  return {
    left: box.left,
    right: box.left + scroller.clientWidth,
    scrollWidth: scroller.scrollWidth,
    clientWidth: scroller.clientWidth,
    viewport: document.documentElement.clientWidth,
    pageScrolls: document.documentElement.scrollWidth > document.documentElement.clientWidth,
    headings: [...document.querySelectorAll('#board thead th')].map((th) => {
      const r = th.getBoundingClientRect();
      return {text: th.textContent.replace(/\\s+/g, ' ').trim(), left: r.left, right: r.right};
    }),
  };
}"""


def test_every_leaderboard_column_is_in_view_at_1280_px_with_ties_marked(
    board: Board, artefacts: Path
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    widths: dict[int, float] = {}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        for width in (1280, 1440, 1920):
            page = patient(browser.new_page(viewport={"width": width, "height": 900}))
            page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda exc: problems.append(str(exc)))
            page.goto(f"{board.url}/challenges/{board.challenge}/leaderboard?phase=dev")
            expect(page.locator("#board tbody tr")).to_have_count(len(PARTICIPANTS))
            m = page.evaluate(MEASURE)
            widths[width] = m["scrollWidth"]
            texts = [h["text"] for h in m["headings"]]
            for name in [*TASKS, *CONDITIONS[1:], "Submitted", "Rank", "Participant", "Score"]:
                assert any(t.startswith(name) for t in texts), (name, texts)
            cut = [
                h
                for h in m["headings"]
                if h["left"] < m["left"] - 0.5 or h["right"] > m["right"] + 0.5
            ]
            assert cut == [], f"at {width} px these headings are cut off: {cut}"
            assert m["scrollWidth"] <= m["clientWidth"], m  # nothing to scroll to
            assert not m["pageScrolls"], m
            expect(page.locator("#board-hint")).to_be_hidden()  # no cue needed: it all fits
            if width == 1280:
                page.screenshot(path=str(artefacts / "leaderboard-1280.png"), full_page=True)
                ranks = page.locator("#board tbody td.col-rank")
                group = [ranks.nth(i).locator(".badge-tie") for i in range(4)]
                expect(group[0]).to_have_text("G1tie group 1: how groups are drawn")
                expect(group[1]).to_have_text(
                    "G1tie group 1, not significantly different from rank 1: how groups are drawn"
                )
                expect(group[1]).to_have_attribute(
                    "title", re.compile(r"^Tie group 1: the paired test .* does not separate")
                )
                expect(group[1]).to_have_attribute("href", "/help/metrics#paired-significance")
                expect(ranks.nth(2)).to_have_text("baseline")
                # 18 of 18 paired episodes against none: separated from the second
                expect(group[3]).to_have_text("G2tie group 2: how groups are drawn")
            page.close()
        browser.close()
    print("leaderboard table width (px) by viewport:", widths)  # for the record (pytest -s)
    assert problems == [], problems


def test_on_a_phone_rank_and_participant_stay_while_the_rest_scrolls_with_a_cue(
    board: Board, artefacts: Path
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        context = patient(
            browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True)
        )
        page = context.new_page()
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))
        page.goto(f"{board.url}/challenges/{board.challenge}/leaderboard?phase=dev")
        frame = page.locator(".board-frame")
        expect(page.locator("#board-hint")).to_be_visible()
        expect(frame).to_have_class("board-frame more-right")
        page.locator("#board").evaluate(
            "t => { const s = t.closest('.table-scroll'); s.scrollLeft = s.scrollWidth; }"
        )
        expect(frame).to_have_class("board-frame more-left")  # scrolled to the far end
        m = page.evaluate(MEASURE)
        by_text = {h["text"]: h for h in m["headings"]}
        rank, user = by_text["Rank"], by_text["Participant"]
        assert abs(rank["left"] - m["left"]) <= 0.5, rank  # sticky: still at the left edge
        assert abs(user["left"] - rank["right"]) <= 0.5, (rank, user)  # right beside it
        submitted = next(h for t, h in by_text.items() if t.startswith("Submitted"))
        assert submitted["right"] <= m["right"] + 0.5  # the last column was reached
        page.screenshot(path=str(artefacts / "leaderboard-phone.png"), full_page=True)
        browser.close()
    assert problems == [], problems
