"""A participant's whole journey in a real browser (Debian's Chromium through Playwright)
against a real server on a free port: register, create a token, submit through the form,
watch the state reach `succeeded` live, find the row on the leaderboard, open the submission.

Screenshots of each page are kept under $MANIEVAL_ARTEFACTS/web (or the test's tmp dir).
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import uvicorn

from manieval.service import embedded_worker_settings
from server.app import create_app
from server.kit.settings import Settings
from testkit.factories import embedded_database
from tests.web.browser_support import (
    CHROMIUM,
    CHROMIUM_ARGS,
    free_port,
    patient,
    require_chromium,
)
from worker.embedded import EmbeddedWorker, InlineQueue

pytestmark = pytest.mark.sim

PASSWORD = "a sturdy passphrase for tests"
EVALUATION_TIMEOUT_MS = 240_000  # a generous bound on a tiny evaluation, never asserted on


@dataclass
class GatedQueue:
    """Holds the evaluation back until the test has the submission page open, so that every
    state change happens while the page is watching."""

    inner: InlineQueue
    held: list[tuple[int, int]] = field(default_factory=list)
    opened: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)

    def enqueue(self, submission_id: int, attempt: int) -> None:
        with self.lock:
            if not self.opened:
                self.held.append((submission_id, attempt))
                return
        self.inner.enqueue(submission_id, attempt)

    def release(self) -> None:
        with self.lock:
            self.opened = True
            held, self.held = self.held, []
        for message in held:
            self.inner.enqueue(*message)


@dataclass
class Server:
    url: str
    gate: GatedQueue


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    settings = Settings(
        dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False, allow_local_policies=True
    )
    sessions = embedded_database(settings, quota_concurrent=3)
    port = free_port()
    # Composed as `manieval serve` composes it, with the gate between the server's outbox and
    # the embedded worker's queue.
    worker = EmbeddedWorker(embedded_worker_settings(settings, port=port))
    gate = GatedQueue(worker.queue)
    app = create_app(settings, sessions=sessions, work=gate)
    # No log_config or log_level: uvicorn would reconfigure this process's logging for the
    # tests that run after this one.
    config = uvicorn.Config(
        app, host="127.0.0.1", port=port, log_config=None, timeout_graceful_shutdown=5
    )
    running = uvicorn.Server(config)
    thread = threading.Thread(target=running.run, name="uvicorn", daemon=True)
    thread.start()
    try:
        while not running.started:
            assert thread.is_alive(), "the server did not start"
            time.sleep(0.02)
        worker.start()  # over loopback HTTP, once the server answers
        yield Server(url=f"http://127.0.0.1:{port}", gate=gate)
    finally:
        running.should_exit = True
        thread.join(timeout=30)
        worker.stop(timeout=30)


def test_register_token_submit_follow_live_and_find_it_on_the_leaderboard(
    server: Server, artefacts: Path
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        context = patient(browser.new_context(viewport={"width": 1280, "height": 900}))
        page = context.new_page()
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))

        def shot(name: str) -> None:
            page.screenshot(path=str(artefacts / f"{name}.png"), full_page=True)

        page.goto(server.url)
        expect(page.get_by_role("heading", name="Challenges", exact=True)).to_be_visible()
        page.keyboard.press("Tab")  # the first stop is the skip link, and it works
        expect(page.get_by_role("link", name="Skip to content")).to_be_focused()
        page.keyboard.press("Enter")
        expect(page.locator("main")).to_be_focused()
        shot("home")

        page.get_by_role("link", name="Register").click()
        page.get_by_label("Username").fill("tester")
        page.get_by_label("Email").fill("tester@example.org")
        page.get_by_label("Password").fill(PASSWORD)
        shot("register")
        page.get_by_role("button", name="Create account").click()
        expect(page).to_have_url(re.compile(r"/account$"))

        page.get_by_label("Token name").fill("laptop")
        page.get_by_role("button", name="Create token").click()
        token = page.locator("#new-token-value")
        expect(token).to_have_text(re.compile(r"^mev_[a-z2-7]{8}_[A-Za-z0-9_-]{43}$"))
        plaintext = token.inner_text()
        shot("account-new-token")
        page.goto(f"{server.url}/account")
        expect(page.get_by_role("rowheader", name="laptop")).to_be_visible()
        assert plaintext not in page.content()  # shown once

        # A team: created through "your team", shown on its page; a rejected invitation is
        # the form again with its problem (and no console error).
        page.get_by_role("navigation", name="Main").get_by_role("link", name="Team").click()
        page.get_by_label("Team name").fill("testers")
        page.get_by_label("Display name").fill("The Testers")
        page.get_by_role("button", name="Create team").click()
        expect(page).to_have_url(re.compile(r"/teams/testers\?done=created$"))
        expect(page.get_by_role("heading", name=re.compile("The Testers"))).to_be_visible()
        page.get_by_label("User name").fill("nobody")
        page.get_by_role("button", name="Invite").click()
        expect(page.get_by_text("no such user")).to_be_visible()
        shot("team")
        page.goto(f"{server.url}/team")
        expect(page.get_by_role("link", name="The Testers")).to_be_visible()

        page.goto(f"{server.url}/challenges/server-tiny")
        shot("challenge")
        page.get_by_role("link", name="Submit a policy").click()
        page.get_by_label("Image reference").fill("local:scripted")
        page.get_by_label("Description (optional)").fill("scripted example, from the browser")
        shot("submit")
        page.get_by_role("button", name="Submit").click()
        expect(page).to_have_url(re.compile(r"/submissions/\d+$"))
        submission_url = page.url
        expect(page.locator("#current-state")).to_have_text("queued")
        expect(page.locator("#live-status")).to_be_visible()  # the event stream is open
        page.evaluate("window.__stillTheSamePage = true")
        server.gate.release()

        expect(page.locator("#current-state")).to_have_text(
            "succeeded", timeout=EVALUATION_TIMEOUT_MS
        )
        timeline = page.locator("#timeline .state")
        expect(timeline).to_have_text(["queued", "launching", "running", "succeeded"])
        expect(page.get_by_role("heading", name="Results")).to_be_visible()
        assert page.evaluate("window.__stillTheSamePage") is True  # no reload
        shot("submission-live-succeeded")

        page.get_by_role("link", name="Server Tiny").first.click()
        page.get_by_role("link", name="Full leaderboard").click()
        row = page.locator("#board tbody tr", has_text="tester")
        expect(row).to_have_count(1)
        expect(row.locator(".ibar")).to_have_count(1)
        shot("leaderboard")
        row.get_by_role("link", name="tester").click()
        expect(page).to_have_url(submission_url)
        expect(page.get_by_role("heading", name="Episodes")).to_be_visible()
        shot("submission")

        phone = patient(browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True))
        small = phone.new_page()
        small.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        small.on("pageerror", lambda exc: problems.append(str(exc)))
        small.goto(f"{server.url}/challenges/server-tiny/leaderboard")
        small.screenshot(path=str(artefacts / "leaderboard-phone.png"), full_page=True)
        browser.close()
    assert problems == [], problems
