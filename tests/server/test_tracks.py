"""Tracks (docs/server.md, Tracks): a challenge groups tracks, each with its own boards and
submit choice; their quota is per track or shared, as the organizer says; the challenge page
shows every track's board; `challenge load` makes a track and the demo's visual challenge is
a track of its core one."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from manieval import demo
from manieval.cli import app
from server.challenges.service import ChallengeOptions, get_challenge, load_challenge
from server.challenges.tracks import get_track, tracks_of
from server.kit.errors import Invalid, NotFound
from server.models import Challenge, User
from testkit.factories import SUITE, make_user, token_for
from tests.server.test_challenge_rules import _done
from tests.web.helpers import browser, csrf_of

IMAGE = "127.0.0.1:5000/team/policy:v1"


def visual_suite(directory: Path) -> Path:
    """The server test suite under another name: a second track's suite."""
    path = directory / "server-tiny-visual.yaml"
    path.write_text(SUITE.read_text().replace("name: server-tiny", "name: server-tiny-visual"))
    return path


def _load(db: Session, suite: Path, **options: object) -> Challenge:
    options = {"quota_per_day": 2, "quota_concurrent": 5, **options}
    challenge = load_challenge(db, suite, ChallengeOptions(**options), seed_secret="s" * 32)  # type: ignore[arg-type]
    db.commit()
    return challenge


@pytest.fixture
def tracks(sessions: sessionmaker[Session], tmp_path: Path) -> None:
    with sessions() as db:
        _load(db, SUITE, track="state")
        _load(db, visual_suite(tmp_path), track="visual", track_of="server-tiny")
        make_user(db, "alice")


def _submit(client: TestClient, headers: dict[str, str], track: str | None) -> dict[str, object]:
    body = {"challenge": "server-tiny", "phase": "dev", "image": IMAGE, "track": track}
    r = client.post("/api/v1/submissions", json=body, headers=headers)
    return {"status": r.status_code, **r.json()}


def test_a_track_joins_its_heads_group_by_name(
    sessions: sessionmaker[Session], tracks: None
) -> None:
    with sessions() as db:
        head = get_challenge(db, slug="server-tiny")
        assert [(t.slug, t.track) for t in tracks_of(db, head)] == [
            ("server-tiny", "state"),
            ("server-tiny-visual", "visual"),
        ]
        assert get_track(db, head, "visual").slug == "server-tiny-visual"
        assert get_track(db, head, "server-tiny-visual").slug == "server-tiny-visual"
        assert get_track(db, head, None) is head
        with pytest.raises(Invalid, match="no track 'depth' \\(it has: state, visual\\)"):
            get_track(db, head, "depth")


def test_a_track_of_a_track_or_of_nothing_is_refused(
    sessions: sessionmaker[Session], tracks: None, tmp_path: Path
) -> None:
    other = tmp_path / "other"
    other.mkdir()
    third = other / "server-tiny-depth.yaml"
    third.write_text(SUITE.read_text().replace("name: server-tiny", "name: server-tiny-depth"))
    with sessions() as db, pytest.raises(Invalid, match="cannot head a group"):
        _load(db, third, track_of="server-tiny-visual")
    with sessions() as db, pytest.raises(NotFound, match="load it first"):
        _load(db, third, track_of="nowhere")
    with sessions() as db, pytest.raises(Invalid, match="share a name"):
        _load(db, third, track="visual", track_of="server-tiny")


def test_the_submit_choice_picks_the_track(
    client: TestClient, sessions: sessionmaker[Session], tracks: None
) -> None:
    headers = token_for(client, "alice")
    made = _submit(client, headers, "visual")
    assert made["status"] == 202, made
    assert made["challenge"] == "server-tiny-visual"
    assert _submit(client, headers, None)["challenge"] == "server-tiny"
    refused = _submit(client, headers, "depth")
    assert refused["status"] == 422
    detail = client.get("/api/v1/challenges/server-tiny-visual", headers=headers).json()
    assert detail["track"] == "visual"
    assert [t["name"] for t in detail["tracks"]] == ["state", "visual"]
    assert detail["quota_shared"] is False


def test_the_quota_is_per_track_unless_the_organizer_shares_it(
    client: TestClient, sessions: sessionmaker[Session], tracks: None
) -> None:
    headers = token_for(client, "alice")
    for track in ("state", "state", "visual"):  # a daily quota of 2 in each track
        assert _submit(client, headers, track)["status"] == 202
    with sessions() as db:
        _load(db, SUITE, quota_shared=True)  # the head's quota, for the whole group
    refused = _submit(client, headers, "visual")
    assert refused["status"] == 429, refused
    assert "'server-tiny' and its tracks (one quota for 2)" in str(refused["error"])
    quota = client.get("/api/v1/challenges/server-tiny-visual", headers=headers).json()
    assert (quota["my_quota"]["per_day_used"], quota["my_quota"]["shared_by"]) == (3, 2)


def test_a_challenge_with_two_tracks_shows_two_boards(
    client: TestClient, sessions: sessionmaker[Session], tracks: None
) -> None:
    with sessions() as db:
        alice = db.scalar(select(User).where(User.username == "alice"))
        assert alice is not None
        for slug in ("server-tiny", "server-tiny-visual"):
            _done(db, alice, get_challenge(db, slug=slug), [True, False])  # the test phase
    page = client.get("/challenges/server-tiny", params={"phase": "test"}).text
    assert "Leaderboard, track state, phase test" in page
    assert "Leaderboard, track visual, phase test" in page
    assert page.count(">alice<") == 2, page  # a row on each board
    other = client.get("/challenges/server-tiny-visual", params={"phase": "test"}).text
    assert "Leaderboard, track state, phase test" in other


def test_the_submit_form_chooses_the_track(client: TestClient, tracks: None) -> None:
    alice = browser(client, "alice")
    form = alice.get("/challenges/server-tiny/submit").text
    assert '<option value="server-tiny-visual"' in form
    fields = {"csrf_token": csrf_of(form), "phase": "dev", "image": IMAGE}
    r = alice.post("/challenges/server-tiny/submit", data={**fields, "track": "server-tiny-visual"})
    assert r.status_code == 303, r.text
    page = alice.get(r.headers["location"]).text
    assert "server-tiny-visual" in page or "Server Tiny Visual" in page


def test_challenge_load_makes_a_track_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    runner = CliRunner()
    r = runner.invoke(app, ["challenge", "load", "--unverified", str(SUITE), "--track", "state"])
    assert r.exit_code == 0, r.output
    args = ["challenge", "load", "--unverified", str(visual_suite(tmp_path)), "--track", "visual"]
    r = runner.invoke(app, [*args, "--track-of", "server-tiny", "--shared-quota"])
    assert r.exit_code == 0, r.output
    assert "tracks: state (server-tiny), visual (server-tiny-visual); one quota shared" in r.output
    r = runner.invoke(
        app, ["challenge", "load", "--unverified", str(SUITE), "--track-of", "server-tiny-visual"]
    )
    assert r.exit_code == 1
    assert "cannot head a group" in r.output


def test_the_demos_visual_challenge_is_a_track_of_its_core_one() -> None:
    core = demo.challenge_options(demo.CORE, episodes=1)
    visual = demo.challenge_options(demo.VISUAL, episodes=1)
    assert (core.track, core.track_of) == ("state", None)
    assert (visual.track, visual.track_of) == ("visual", "maniskill-core")
    assert demo.TRACKS == (demo.CORE, demo.VISUAL)  # the head is loaded first
