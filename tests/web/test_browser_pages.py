"""Pages a newcomer meets, in Chromium at 1,280 px and on a 390x844 phone: a reload after
creating a token, an error page that keeps who is logged in, the submit form's method fields
styled as the others, and on a phone the key columns of the tables in view (or a hint that the
table scrolls), chart labels of a readable size, no console errors."""

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

PHONE = {"width": 390, "height": 844}
MIN_LABEL_PX = 10.0
WAIT_MS = 60_000  # a generous bound on a page of a busy machine, never asserted on


@dataclass
class Site:
    url: str
    submission_id: int


@pytest.fixture
def site(tmp_path: Path) -> Iterator[Site]:
    """A server with alice's two finished submissions on server-tiny, one with a long image."""
    settings = Settings(dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False)
    sessions = embedded_database(settings, quota_per_day=10)
    with sessions() as db:
        alice = make_user(db, "alice")
        tiny = db.scalar(
            select(Challenge)
            .options(selectinload(Challenge.phases))
            .where(Challenge.slug == "server-tiny")
        )
        assert tiny is not None
        first = finished(db, alice, tiny, [True, False])
        finished(db, alice, tiny, [True, True])
        submission_id = first.id
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield Site(url=url, submission_id=submission_id)


def _watch(page: Any, problems: list[str]) -> None:
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda exc: problems.append(str(exc)))


def _log_in(page: Any, url: str) -> None:
    page.goto(f"{url}/login")
    page.fill("#login", "alice")
    page.fill("#password", PASSWORD)
    page.click("main form button[type=submit]")
    page.wait_for_url(re.compile(r"/account$"), timeout=WAIT_MS)


def test_reloading_a_new_token_shows_the_account_and_error_pages_keep_the_account(
    site: Site,
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        context = patient(chromium.new_context(viewport={"width": 1280, "height": 800}))
        page = context.new_page()
        _watch(page, problems)
        _log_in(page, site.url)
        page.get_by_label("Token name").fill("laptop")
        page.get_by_role("button", name="Create token").click()
        token = page.locator("#new-token-value")
        expect(token).to_be_visible(timeout=WAIT_MS)
        plaintext = token.inner_text()
        expect(page).to_have_url(re.compile(r"/account#tokens$"))  # the address a reload gets

        page.reload()
        expect(page.get_by_role("heading", name="API tokens")).to_be_visible(timeout=WAIT_MS)
        expect(page.get_by_role("rowheader", name="laptop")).to_have_count(1)  # not sent again
        assert plaintext not in page.content()
        nav = page.get_by_role("navigation", name="Main")
        expect(nav.get_by_role("link", name="Account (alice)")).to_be_visible()

        page.goto(f"{site.url}/account/tokens")  # the form's address typed in: the account
        expect(page).to_have_url(re.compile(r"/account#tokens$"))

        # An error page (a 405 here, which Chromium logs as a failed load: not watched) shows
        # the same navigation as every page, with the account's name and its team.
        refused = context.new_page()
        answer = refused.goto(f"{site.url}/team/leave")
        assert answer is not None
        assert answer.status == 405
        nav = refused.get_by_role("navigation", name="Main")
        expect(nav.get_by_role("link", name="Account (alice)")).to_be_visible()
        expect(nav.get_by_role("link", name="Team")).to_be_visible()
        expect(nav.get_by_role("button", name="Log out")).to_be_visible()

        # The method fields look like the image field above them.
        page.goto(f"{site.url}/challenges/server-tiny/submit")
        looks = page.evaluate(
            """() => ["image", "method", "paper_url", "code_url"].map((id) => {
                const s = getComputedStyle(document.getElementById(id));
                return [s.borderTopColor, s.borderTopWidth, s.paddingLeft, s.width, s.borderRadius];
            })"""
        )
        assert all(look == looks[0] for look in looks), looks
        chromium.close()
    assert problems == [], problems


def _outside(page: Any, selector: str) -> list[str]:
    """The elements of `selector` (headings of key columns) not wholly inside the viewport."""
    found: list[str] = page.evaluate(
        """(selector) => [...document.querySelectorAll(selector)].filter((e) => {
            const r = e.getBoundingClientRect();
            return r.width === 0 || r.left < 0 || r.right > window.innerWidth;
        }).map((e) => e.textContent.trim())""",
        selector,
    )
    return found


def _hidden_overflow(page: Any) -> list[str]:
    """Tables wider than their box whose scroll hint is not shown."""
    found: list[str] = page.evaluate(
        """() => [...document.querySelectorAll(".table-scroll")].filter((s) => {
            const hint = s.closest("[data-scroll-cue]")?.querySelector(".scroll-hint");
            return s.scrollWidth > s.clientWidth + 1 && !(hint && hint.checkVisibility());
        }).map((s) => s.getAttribute("aria-label") || s.getAttribute("aria-labelledby"))"""
    )
    return found


def _smallest_chart_label_px(page: Any) -> float:
    """The rendered size of the smallest chart label: its font size times the SVG's scale."""
    size: float = page.evaluate(
        """() => Math.min(...[...document.querySelectorAll(".chart svg text")].map(
            (t) => parseFloat(getComputedStyle(t).fontSize) * t.getScreenCTM().a))"""
    )
    return size


def _page_width(page: Any) -> int:
    width: int = page.evaluate("document.documentElement.scrollWidth")
    return width


def test_on_a_phone_key_columns_are_in_view_and_chart_labels_readable(site: Site) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        phone = patient(chromium.new_context(viewport=PHONE, is_mobile=True, has_touch=True))
        page = phone.new_page()
        _watch(page, problems)
        _log_in(page, site.url)

        page.goto(f"{site.url}/submissions")
        expect(page.locator("table.submissions tbody tr")).to_have_count(2, timeout=WAIT_MS)
        key = (
            "table.submissions thead th:nth-child(-n+3), "
            "table.submissions tbody tr > :nth-child(-n+3)"
        )
        assert _outside(page, key) == []  # submission, state and score
        assert _hidden_overflow(page) == []
        assert _page_width(page) <= PHONE["width"]

        page.goto(f"{site.url}/challenges/server-tiny")
        expect(page.get_by_role("heading", name="Phases and deadlines")).to_be_visible()
        for label in ("Table of phases", "Table of tasks"):
            region = f'[aria-label="{label}"]'
            assert _outside(page, f"{region} thead th:nth-child(-n+2)") == [], label
        assert _hidden_overflow(page) == []
        assert _page_width(page) <= PHONE["width"]
        assert _smallest_chart_label_px(page) >= MIN_LABEL_PX  # the best score over time

        page.goto(f"{site.url}/submissions/{site.submission_id}")
        expect(page.get_by_role("heading", name="Episodes")).to_be_visible()
        assert _smallest_chart_label_px(page) >= MIN_LABEL_PX  # success per task
        assert _hidden_overflow(page) == []
        assert _page_width(page) <= PHONE["width"]
        chromium.close()
    assert problems == [], problems
