"""An organizer disqualifies a submission from its page in Chromium: the reason is required,
the confirmation can be declined, and the board then shows the row unranked with the reason."""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.orm import selectinload

from server.app import create_app
from server.kit.settings import Settings
from server.models import Challenge
from testkit.factories import PASSWORD, RecordingQueue, embedded_database, make_user
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium, serving
from tests.web.helpers import finished

WAIT_MS = 60_000  # a generous bound on a page of a busy machine, never asserted on
WHY = "the policy reads the episode seed"


@dataclass
class Site:
    url: str
    submission_id: int


@pytest.fixture
def site(tmp_path: Path) -> Iterator[Site]:
    """A server with alice's finished submission on server-tiny, and an admin."""
    settings = Settings(dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False)
    sessions = embedded_database(settings, quota_per_day=10)
    with sessions() as db:
        alice = make_user(db, "alice")
        make_user(db, "judge", admin=True)
        tiny = db.scalar(
            select(Challenge)
            .options(selectinload(Challenge.phases))
            .where(Challenge.slug == "server-tiny")
        )
        assert tiny is not None
        submission_id = finished(db, alice, tiny, [True, False]).id
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield Site(url=url, submission_id=submission_id)


def test_an_admin_disqualifies_from_the_page_with_a_reason_and_a_confirmation(
    site: Site,
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    answers: list[bool] = [False, True]  # decline the first confirmation, accept the second

    def confirm(dialog: Any) -> None:
        (dialog.accept if answers.pop(0) else dialog.dismiss)()

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(chromium.new_context(viewport={"width": 1280, "height": 800})).new_page()
        page.goto(f"{site.url}/login")
        page.fill("#login", "judge")
        page.fill("#password", PASSWORD)
        page.click("main form button[type=submit]")
        page.wait_for_url(re.compile(r"/account$"), timeout=WAIT_MS)
        page.goto(f"{site.url}/submissions/{site.submission_id}")
        page.on("dialog", confirm)
        button = page.get_by_role("button", name="Disqualify", exact=True)
        button.click()  # no reason: the browser asks for one, nothing is sent
        assert answers == [False, True]
        page.get_by_label("Reason to disqualify").fill(WHY)
        button.click()  # declined
        expect(page.locator("#moderation")).to_have_count(0)
        assert answers == [True]
        button.click()  # accepted
        expect(page.locator("#moderation")).to_contain_text(WHY, timeout=WAIT_MS)
        expect(page.get_by_role("button", name="Reinstate")).to_be_visible()
        page.goto(f"{site.url}/challenges/server-tiny/leaderboard?phase=dev")
        row = page.locator("tr.disqualified-row")
        expect(row).to_contain_text("disqualified")
        expect(row).to_contain_text(WHY)
        chromium.close()
