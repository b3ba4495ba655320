"""The console in Chromium, on one served app: at 1,280 px an organizer changes a quota and
disables an account through the forms; at 1,280 px and on a 390x844 phone every console page
keeps its key columns in view (or says the table scrolls), nothing wider than the screen, and
no console errors. Screenshots are kept under $MANIEVAL_ARTEFACTS/web (or the test's tmp dir)."""

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
from server.console.users import disable_account
from server.kit.settings import Settings
from server.models import Challenge
from testkit.factories import PASSWORD, RecordingQueue, embedded_database, make_user
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium, serving
from tests.web.helpers import finished
from tests.web.test_browser_pages import PHONE, WAIT_MS, _hidden_overflow, _outside, _page_width

DESKTOP = {"width": 1280, "height": 800}


@dataclass
class Console:
    url: str
    alice_id: int
    mallory_id: int


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    """One app for the module: an organizer, alice with two finished submissions, mallory
    disabled with a long reason, and a few audit records."""
    data = tmp_path_factory.mktemp("console")
    settings = Settings(dev_mode=True, data_dir=data, cookie_secure=False)
    sessions = embedded_database(settings, quota_per_day=10)
    with sessions() as db:
        judge = make_user(db, "judge", admin=True)
        alice = make_user(db, "alice")
        mallory = make_user(db, "mallory_with_a_rather_long_name", verified=False)
        tiny = db.scalar(
            select(Challenge)
            .options(selectinload(Challenge.phases))
            .where(Challenge.slug == "server-tiny")
        )
        assert tiny is not None
        finished(db, alice, tiny, [True, False])
        finished(db, alice, tiny, [True, True])
        reason = (
            "Submitted the same policy from several accounts to get around the daily quota. " * 3
        )
        disable_account(db, user=mallory, by=judge, reason=reason)
        db.commit()
        ids = (alice.id, mallory.id)
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield Console(url=url, alice_id=ids[0], mallory_id=ids[1])


def _watch(page: Any, problems: list[str]) -> None:
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda exc: problems.append(str(exc)))


def _log_in(page: Any, url: str) -> None:
    page.goto(f"{url}/login")
    page.fill("#login", "judge")
    page.fill("#password", PASSWORD)
    page.click("main form button[type=submit]")
    page.wait_for_url(re.compile(r"/account$"), timeout=WAIT_MS)


def _pages(console: Console) -> list[tuple[str, str]]:
    """Each console page with the selector of its key cells (first columns of its tables)."""
    two = "thead th:nth-child(-n+2), tbody tr > :nth-child(-n+2)"
    return [
        ("/admin", f".console-phases {two}, table.audit {two}"),
        ("/admin/challenges/server-tiny", "main h1, .console-phase h3"),
        ("/admin/users", f"table.console-users {two}"),
        (f"/admin/users/{console.mallory_id}", f".facts dt, table.audit {two}"),
        ("/admin/audit", f"table.audit {two}"),
        ("/admin/submissions?user=alice", "table.submissions thead th:nth-child(-n+3)"),
    ]


@pytest.mark.parametrize("viewport", [DESKTOP, PHONE], ids=["desktop", "phone"])
def test_console_pages_fit_the_screen_with_key_columns_in_view(
    console: Console, viewport: dict[str, int], artefacts: Path
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        phone = viewport == PHONE
        context = patient(chromium.new_context(viewport=viewport, is_mobile=phone, has_touch=phone))
        page = context.new_page()
        _watch(page, problems)
        _log_in(page, console.url)
        for path, key in _pages(console):
            page.goto(f"{console.url}{path}")
            expect(page.get_by_role("navigation", name="Console")).to_be_visible(timeout=WAIT_MS)
            assert page.locator(key).count() > 0, path
            assert _outside(page, key) == [], path
            assert _hidden_overflow(page) == [], path
            assert _page_width(page) <= viewport["width"], path
            name = re.sub(r"\W+", "-", path.strip("/")).strip("-")
            page.screenshot(path=artefacts / f"{name}-{viewport['width']}.png", full_page=True)
        chromium.close()
    assert problems == [], problems


def test_an_organizer_changes_a_quota_and_disables_an_account_in_the_browser(
    console: Console,
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(chromium.new_context(viewport=DESKTOP)).new_page()
        _watch(page, problems)
        page.on("dialog", lambda dialog: dialog.accept())  # the forms' confirmations
        _log_in(page, console.url)
        page.get_by_role("navigation", name="Main").get_by_role("link", name="Console").click()
        expect(page.get_by_role("heading", name="Console", exact=True)).to_be_visible()
        page.get_by_role("link", name="Settings").first.click()
        page.get_by_label("Submissions a day").fill("0")
        page.get_by_role("button", name="Save settings").click()
        expect(page.locator("#quota_per_day-error")).to_contain_text("a whole number from 1")
        page.get_by_label("Submissions a day").fill("12")
        page.get_by_role("button", name="Save settings").click()
        expect(page.get_by_role("status")).to_contain_text("settings are saved")
        expect(page.get_by_label("Submissions a day")).to_have_value("12")

        page.goto(f"{console.url}/admin/users?q=alice")
        page.get_by_role("link", name="alice", exact=True).click()
        page.get_by_label("Reason").fill("Shared the test seeds")
        page.get_by_role("button", name="Disable the account").click()
        expect(page.get_by_role("status")).to_contain_text("The account is disabled")
        expect(page.locator(".facts")).to_contain_text("Shared the test seeds")
        page.get_by_role("button", name="Enable the account").click()
        expect(page.get_by_role("status")).to_contain_text("enabled again")

        page.goto(f"{console.url}/admin")
        expect(page.locator("table.audit")).to_contain_text("user.enable")
        expect(page.locator("table.audit")).to_contain_text("quota_per_day: 10 → 12")
        chromium.close()
    assert problems == [], problems
