"""The leaderboard page's content is rendered once per distinct content and kept, its header
per request: a viewer never sees another's name or form token, and a kept content never
outlives what it shows (a new row, a new rank, the challenge's title)."""

from __future__ import annotations

import re

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import Challenge
from testkit.factories import RecordingQueue, fake_resolve_for, make_user
from tests.web.helpers import browser, csrf_of, finished

PAGE = "/challenges/server-tiny/leaderboard?phase=dev"
SORTED = PAGE + "&sort=user&dir=desc&per_page=10"


def _main(html: str) -> str:
    return html.split("<main", 1)[1].split("</main>", 1)[0]


def _fresh_main(settings: Settings, sessions: sessionmaker[Session], url: str) -> str:
    """The page's content as an app that has kept nothing renders it."""
    app = create_app(
        settings,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app, base_url="http://testserver") as fresh:
        return _main(fresh.get(url).text)


def test_each_viewer_gets_their_own_header_on_kept_content(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    for name in ("alice", "bob"):
        finished(db, make_user(db, name), tiny, [True, False])
    alice, bob, visitor = browser(client, "alice"), browser(client, "bob"), browser(client)
    seen = {who: c.get(PAGE).text for who, c in (("alice", alice), ("bob", bob), ("-", visitor))}
    assert _main(seen["alice"]) == _main(seen["bob"]) == _main(seen["-"])  # one content
    assert "Account (alice)" in seen["alice"]
    assert "Account (alice)" not in seen["bob"] + seen["-"]
    assert "Account (bob)" in seen["bob"]
    assert "Log in" in seen["-"]
    assert csrf_of(seen["alice"]) != csrf_of(seen["bob"])


def test_kept_content_follows_the_board_and_the_challenge(
    client: TestClient,
    db: Session,
    tiny: Challenge,
    settings: Settings,
    sessions: sessionmaker[Session],
) -> None:
    ada = make_user(db, "ada")
    finished(db, ada, tiny, [True, False])
    for url in (PAGE, SORTED):
        assert _main(client.get(url).text) == _fresh_main(settings, sessions, url)
    finished(db, make_user(db, "zed"), tiny, [True, True])  # ranked above ada
    for url in (PAGE, SORTED):
        main = _main(client.get(url).text)
        assert re.findall(r'<a href="/submissions/\d+">([^<]+)</a>', main) == (["zed", "ada"])
        assert main == _fresh_main(settings, sessions, url)
    finished(db, ada, tiny, [True, True])  # ada's row replaced: as many rows as before
    for url in (PAGE, SORTED):
        assert _main(client.get(url).text) == _fresh_main(settings, sessions, url)
    tiny.title = "Renamed Tiny"
    db.commit()
    assert "Renamed Tiny" in _main(client.get(PAGE).text)
