"""What every page shares: security headers, no inline script, HTML errors for pages and JSON
for the API, CSRF on every form, escaping, labels and landmarks."""

from __future__ import annotations

import re
from html.parser import HTMLParser

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server.models import Challenge, State
from testkit.factories import make_user
from tests.web.helpers import browser, csrf_of, finished

HOSTILE = '<script>alert("x")</script><img src=x onerror=alert(1)>'


class Page(HTMLParser):
    """What the accessibility and script checks look at in a page."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.inline_scripts = 0
        self.handlers: list[str] = []
        self.inputs: list[dict[str, str | None]] = []
        self.labels: set[str] = set()
        self.ids: set[str] = set()
        self.tags: list[str] = []
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        found = dict(attrs)
        self.tags.append(tag)
        if found.get("id"):
            self.ids.add(str(found["id"]))
        self.handlers += [name for name, _ in attrs if name.startswith("on")]
        if tag == "script" and not found.get("src"):
            self.inline_scripts += 1
        if tag in ("input", "select", "textarea") and found.get("type") not in ("hidden",):
            self.inputs.append(found)
        if tag == "label" and found.get("for"):
            self.labels.add(str(found["for"]))


def pages_of(client: TestClient, db: Session, challenge: Challenge) -> list[str]:
    s = finished(db, make_user(db, "alice"), challenge, [True, False])
    return [
        "/",
        "/login",
        "/register",
        f"/challenges/{challenge.slug}",
        f"/challenges/{challenge.slug}/leaderboard",
        f"/challenges/{challenge.slug}/submit",
        f"/submissions/{s.id}",
        "/submissions",
        "/account",
        "/no-such-page",
    ]


def test_pages_forbid_inline_script_and_have_labels_landmarks_and_a_skip_link(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    pages = pages_of(client, db, tiny)
    alice = browser(client, "alice")
    for path in pages:
        r = alice.get(path)
        assert r.headers["content-type"].startswith("text/html"), path
        csp = r.headers["content-security-policy"]
        assert "script-src 'self'" in csp, path
        assert "unsafe-inline" not in csp, path
        assert "frame-ancestors 'none'" in csp
        page = Page(r.text)
        assert page.inline_scripts == 0, path
        assert page.handlers == [], path
        assert 'href="#main"' in r.text, path
        assert {"main", "nav", "h1"} <= set(page.tags), path
        for field in page.inputs:
            labelled = field.get("id") in page.labels or field.get("aria-label")
            inside_label = field.get("type") == "radio"  # wrapped in their <label>
            assert labelled or inside_label, f"{path}: unlabelled {field}"


def test_unknown_pages_get_html_errors_and_the_api_keeps_json(client: TestClient) -> None:
    page = client.get("/no-such-page")
    assert page.status_code == 404
    assert page.headers["content-type"].startswith("text/html")
    assert "Not found" in page.text
    api = client.get("/api/v1/no-such-thing")
    assert api.status_code == 404
    assert api.json()["error"]["code"] == "not_found"
    assert client.get("/api/v1/challenges/nope").json()["error"]["code"] == "not_found"
    bad = client.get("/challenges/server-tiny/leaderboard?page=0")
    assert bad.status_code == 422
    assert bad.headers["content-type"].startswith("text/html")


def test_form_posts_without_the_right_csrf_token_are_refused(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    make_user(db, "alice")
    stranger = browser(client)
    refused = stranger.post("/login", data={"login": "alice", "password": "x" * 12})
    assert refused.status_code == 403
    assert "security token" in refused.text
    alice = browser(client, "alice")
    for action, fields in [
        ("/account/tokens", {"name": "forged-token-name"}),
        ("/logout", {}),
        ("/challenges/server-tiny/submit", {"image": "127.0.0.1:5000/a/b:v1", "phase": "dev"}),
    ]:
        for token in ("", "forged"):
            r = alice.post(action, data={"csrf_token": token, **fields})
            assert r.status_code == 403, action
    assert "forged-token-name" not in alice.get("/account").text
    assert "No submissions yet" in alice.get("/submissions").text
    # Another session's token is no good either.
    other = browser(client, "alice")
    theirs = csrf_of(other.get("/account").text)
    assert (
        alice.post("/account/tokens", data={"csrf_token": theirs, "name": "x"}).status_code == 403
    )


def test_user_text_is_escaped_everywhere_it_is_shown(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    alice_user = make_user(db, "alice")
    s = finished(
        db,
        alice_user,
        tiny,
        [False],
        state=State.FAILED,
        reason=HOSTILE,
        log_tail=HOSTILE,
        description=HOSTILE,
    )
    alice = browser(client, "alice")
    token = csrf_of(alice.get("/account").text)
    alice.post("/account/tokens", data={"csrf_token": token, "name": HOSTILE})
    for path in (f"/submissions/{s.id}", "/account", f"/submissions/{s.id}/outcome"):
        text = alice.get(path).text
        assert "<script>alert" not in text, path
        assert "<img src=x" not in text, path
        assert "&lt;script&gt;" in text, path
    assert not re.search(r"<script(?![^>]*\bsrc=)", alice.get(f"/submissions/{s.id}").text)


def test_the_static_files_are_served_with_a_content_version(client: TestClient) -> None:
    home = client.get("/").text
    css = re.search(r'href="(/static/style\.css\?v=[0-9a-f]{12})"', home)
    js = re.search(r'src="(/static/app\.js\?v=[0-9a-f]{12})"', home)
    assert css
    assert js
    assert client.get(css.group(1)).status_code == 200
    assert "EventSource" in client.get(js.group(1)).text
    assert client.get("/favicon.ico", follow_redirects=False).status_code == 301
