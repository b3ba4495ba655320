"""The API reference at /docs works offline: Swagger UI from the installed package, started by
a script file under the pages' CSP, with no request leaving 127.0.0.1."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from server.app import create_app
from server.kit.apidocs import mount_api_docs
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from testkit.factories import RecordingQueue
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium, serving


def test_docs_page_uses_local_assets_and_no_inline_script(client: TestClient) -> None:
    r = client.get("/docs")
    assert r.status_code == 200
    html = r.text
    sources = re.findall(r'<(?:script|link)[^>]+(?:src|href)="([^"]+)"', html)
    assert sources, html
    assert all(urlsplit(s).netloc == "" for s in sources), sources  # nothing from elsewhere
    assert re.search(r"<script(?![^>]*\bsrc=)[^>]*>", html) is None  # no inline script
    csp = r.headers["content-security-policy"]
    assert "script-src 'self';" in csp
    assert "img-src 'self' data:;" in csp
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
        served = client.get(f"/docs/assets/{asset}")
        assert served.status_code == 200, asset
        assert len(served.content) > 10_000


def test_the_openapi_declares_the_api_token_and_protected_operations_use_it(
    client: TestClient,
) -> None:
    document = client.get("/openapi.json").json()
    scheme = document["components"]["securitySchemes"]["apiToken"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    operations = {
        (method.upper(), path): op.get("security", [])
        for path, methods in document["paths"].items()
        for method, op in methods.items()
    }
    for protected in [
        ("GET", "/api/v1/me"),
        ("POST", "/api/v1/tokens"),
        ("POST", "/api/v1/submissions"),
        ("GET", "/api/v1/submissions/{submission_id}/episodes"),
        ("POST", "/api/v1/teams"),
    ]:
        assert {"apiToken": []} in operations[protected], protected
    assert operations[("POST", "/api/v1/users")] == []  # registering needs no token
    assert not any(path.startswith("/internal/") for _, path in operations)  # workers' only


def test_mounting_over_fastapis_own_docs_page_is_refused() -> None:
    with pytest.raises(ValueError, match="docs_url=None"):
        mount_api_docs(FastAPI())


@pytest.fixture
def served(tmp_path: Path) -> Iterator[str]:
    settings = Settings(dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False)
    settings.data_dir.mkdir(parents=True)
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield url


def test_docs_page_lists_the_operations_with_every_other_host_blocked(served: str) -> None:
    require_chromium()
    from playwright.sync_api import Route, expect, sync_playwright

    problems: list[str] = []
    elsewhere: list[str] = []

    def only_loopback(route: Route) -> None:
        if urlsplit(route.request.url).hostname == "127.0.0.1":
            route.continue_()
        else:
            elsewhere.append(route.request.url)
            route.abort()

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(browser.new_page(viewport={"width": 1280, "height": 900}))
        page.route("**/*", only_loopback)
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))
        page.goto(f"{served}/docs")
        operations = page.locator(".opblock-summary-path")
        expect(operations.first).to_be_visible(timeout=60_000)
        paths = operations.all_inner_texts()
        assert any("/api/v1/challenges/{slug}/leaderboard" in path for path in paths), paths
        expect(page.get_by_role("heading", name=re.compile("^ManiEval"))).to_be_visible()
        # The API token's scheme is declared: Swagger offers to authorize with it.
        page.get_by_role("button", name=re.compile("Authorize")).first.click()
        expect(page.get_by_text("apiToken (http, Bearer)")).to_be_visible()
        browser.close()
    assert elsewhere == [], elsewhere
    assert problems == [], problems
