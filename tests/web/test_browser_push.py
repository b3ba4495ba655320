"""A participant's own policy through the web, in Chromium, against a real `manieval serve` with
the registry and Podman it started: the submit page shows the commands with their name and the
registry filled in; the image pushed with them, entered in the form, is followed live to
`succeeded` and ranked.

Screenshots are kept under $MANIEVAL_ARTEFACTS/web (or the test's tmp dir).
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.cli.push_support import CHALLENGE, TAG, Embedded, build_template, embedded_service
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium

pytestmark = pytest.mark.sim

PASSWORD = "a sturdy passphrase for tests"
EVALUATION_TIMEOUT_MS = 300_000  # a generous bound on a tiny evaluation, never asserted on


@pytest.fixture(scope="module")
def embedded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Embedded]:
    with embedded_service(tmp_path_factory.mktemp("web-push")) as service:
        yield service


def podman(*args: str, stdin: str | None = None, env: dict[str, str]) -> str:
    done = subprocess.run(
        ["podman", *args],
        input=stdin,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_the_submit_page_leads_from_a_pushed_image_to_a_ranked_submission(
    embedded: Embedded, artefacts: Path
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    url = embedded.server.url
    local = f"localhost/web-policy:{TAG}"
    build_template(embedded, local)
    engine_env = {"REGISTRY_AUTH_FILE": str(embedded.work / "auth-web.json")}
    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(browser.new_context(viewport={"width": 1280, "height": 900})).new_page()
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))

        page.goto(f"{url}/register")
        page.get_by_label("Username").fill("webber")
        page.get_by_label("Email").fill("webber@example.org")
        page.get_by_label("Password").fill(PASSWORD)
        page.get_by_role("button", name="Create account").click()
        expect(page).to_have_url(re.compile(r"/account$"))
        page.get_by_label("Token name").fill("podman")
        page.get_by_role("button", name="Create token").click()
        token = page.locator("#new-token-value").inner_text()

        page.goto(f"{url}/challenges/{CHALLENGE}/submit")
        commands = page.locator("#push-commands")
        expect(commands).to_contain_text(f"manieval login -u webber --server {url}")
        expect(commands).to_contain_text(f"manieval push my-policy:v1 --challenge {CHALLENGE}")
        login = f"podman login --tls-verify=false -u webber {embedded.registry}"
        expect(commands).to_contain_text(login)
        pushed = f"{embedded.registry}/webber/my-policy:v1"
        expect(commands).to_contain_text(f"podman push --tls-verify=false my-policy:v1 {pushed}")
        page.screenshot(path=str(artefacts / "submit-push-commands.png"), full_page=True)

        # What the page says, with the API token as the password.
        podman(*login.split()[1:], "--password-stdin", stdin=token + "\n", env=engine_env)
        podman("push", "--quiet", "--tls-verify=false", local, pushed, env=engine_env)

        page.get_by_label("Image reference").fill(pushed)
        page.get_by_role("button", name="Submit").click()
        expect(page).to_have_url(re.compile(r"/submissions/\d+$"))
        expect(page.locator("#current-state")).to_have_text(
            "succeeded", timeout=EVALUATION_TIMEOUT_MS
        )
        expect(page.locator("#timeline .state").last).to_have_text("succeeded")
        pinned = f"{embedded.registry}/webber/my-policy@sha256:"
        expect(page.get_by_text(pinned).first).to_be_visible()  # what runs...
        expect(page.locator("#provenance").get_by_text(pinned)).to_be_visible()  # ...and ran
        page.screenshot(path=str(artefacts / "submission-pushed-succeeded.png"), full_page=True)

        page.goto(f"{url}/challenges/{CHALLENGE}/leaderboard")
        expect(page.locator("#board tbody tr", has_text="webber")).to_have_count(1)
        browser.close()
    assert problems == [], problems
