"""Episode videos end to end, composed as `manieval serve` composes it: the embedded worker runs
the bundled `local:scripted` policy on a suite that records one episode per task and condition,
uploads the video through ``/internal/v1``, the server keeps it in its data directory and serves
it to whoever may see the submission; Chromium plays it on the submission's page.

One module-wide service and two small evaluations (one rendered episode each, at most 30
steps) keep the rendering cost low.
"""

from __future__ import annotations

import io
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from evaluator.video import poster_name
from internal_api.schemas import FINAL_STATES
from manieval.service import Service
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from testkit.factories import PASSWORD, make_user
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium

pytestmark = pytest.mark.sim

API = "/api/v1"
FINAL = {state.value for state in FINAL_STATES}  # as the API spells them
NAME = "nominal--PickCube-v1--ep0.mp4"
SUITE = """\
name: video-tiny
title: Video Tiny
version: 1
tasks:
  - {env_id: PickCube-v1, max_episode_steps: 30, episodes: 2}
phases:
  dev: {seeds: {kind: public, start: 0}}
  test: {seeds: {kind: secret}}
videos: 1
limits: {connect_timeout_s: 60, first_call_timeout_s: 60, call_timeout_s: 5, budget_s: 300}
"""
METHOD = {
    "method": "Scripted grasp",
    "paper_url": "https://example.org/paper",
    "code_url": "https://example.org/code",
}
EVALUATION_TIMEOUT_S = 300.0  # a generous bound on two tiny evaluations, never asserted on


@dataclass
class Recorded:
    url: str
    data_dir: Path
    owner: dict[str, str]  # alice's API token header
    stranger: dict[str, str]  # bob's
    private_dev: int  # alice's, private, public seeds
    public_dev: int  # alice's, public, public seeds
    public_test: int  # alice's, public, secret seeds: recorded nothing


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def token(client: httpx.Client, username: str) -> dict[str, str]:
    r = client.post(f"{API}/auth/token", json={"login": username, "password": PASSWORD})
    assert r.status_code == 201, r.text
    return {"Authorization": f"Bearer {r.json()['token']}"}


def wait_final(client: httpx.Client, headers: dict[str, str], sid: int) -> dict[str, Any]:
    deadline = time.monotonic() + EVALUATION_TIMEOUT_S
    while time.monotonic() < deadline:
        body: dict[str, Any] = client.get(f"{API}/submissions/{sid}", headers=headers).json()
        if body["state"] in FINAL:
            return body
        time.sleep(0.2)
    raise AssertionError(f"submission {sid} did not finish in {EVALUATION_TIMEOUT_S} s")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Recorded]:
    data_dir = tmp_path_factory.mktemp("videos-service")
    settings = Settings(
        dev_mode=True, data_dir=data_dir, cookie_secure=False, allow_local_policies=True
    )
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    suite = data_dir / "video-tiny.yaml"
    suite.write_text(SUITE)
    with sessions() as db:
        load_challenge(
            db,
            suite,
            ChallengeOptions(quota_concurrent=3),
            seed_secret=settings.secret("seed_secret"),
        )
        db.commit()
        make_user(db, "alice")
        make_user(db, "bob")
    service = None
    for _ in range(5):  # another process may take the free port first
        service = Service(settings, port=free_port(), sessions=sessions)
        if service.start():
            break
        service.stop()
        service = None
    assert service is not None, "the service did not start"
    try:
        with httpx.Client(base_url=service.url, timeout=60) as client:
            owner, stranger = token(client, "alice"), token(client, "bob")
            ids = []
            for phase, public in (("dev", False), ("dev", True), ("test", True)):
                body = {"challenge": "video-tiny", "phase": phase, "image": "local:scripted"}
                body |= {"public": public} | (METHOD if not public else {})
                r = client.post(f"{API}/submissions", headers=owner, json=body)
                assert r.status_code == 202, r.text
                ids.append(r.json()["id"])
            for sid in ids:
                assert wait_final(client, owner, sid)["state"] == "succeeded"
        yield Recorded(service.url, data_dir, owner, stranger, *ids)
    finally:
        service.stop()


def test_the_worker_records_the_first_episode_and_the_server_keeps_it_per_attempt(
    recorded: Recorded,
):
    import imageio.v2 as imageio

    stored = recorded.data_dir / "videos" / str(recorded.private_dev) / "1" / NAME
    assert stored.is_file()
    # The first episode only, nothing partial, with the poster the evaluator made of it;
    # beside it, every episode's trajectories (docs/trajectories.md), one task run's here.
    trajectories = stored.parent / "trajectories"
    poster = stored.with_name(poster_name(NAME))
    assert sorted(stored.parent.iterdir()) == [stored, poster, trajectories]
    assert poster.stat().st_mtime_ns == stored.stat().st_mtime_ns
    assert sorted(p.name for p in trajectories.iterdir()) == [
        "nominal--PickCube-v1.h5",
        "nominal--PickCube-v1.json",
    ]
    with httpx.Client(base_url=recorded.url, timeout=60) as client:
        r = client.get(f"{API}/submissions/{recorded.private_dev}/videos", headers=recorded.owner)
        assert r.status_code == 200, r.text
        [video] = r.json()["videos"]
        episodes = client.get(
            f"{API}/submissions/{recorded.private_dev}/episodes", headers=recorded.owner
        ).json()["items"]
    first = next(e for e in episodes if e["index"] == 0)
    assert video == {
        "condition": "nominal",
        "env_id": "PickCube-v1",
        "episode": 0,
        "seed": first["seed"],
        "success_once": first["success_once"],
        "success_at_end": first["success_at_end"],
        "steps": first["steps"],
        "failure": None,
        "url": f"{API}/submissions/{recorded.private_dev}/videos/{NAME}",
        "poster": f"{API}/submissions/{recorded.private_dev}/videos/{NAME}/poster",
    }
    assert first["seed"] == 0
    assert len(imageio.mimread(stored)) == first["steps"] + 1  # the reset state first


def test_videos_are_shown_as_the_submission_is_owner_always_others_when_public(
    recorded: Recorded,
):
    private = f"{API}/submissions/{recorded.private_dev}/videos"
    public = f"{API}/submissions/{recorded.public_dev}/videos"
    secret = f"{API}/submissions/{recorded.public_test}/videos"
    with httpx.Client(base_url=recorded.url, timeout=60) as client:
        r = client.get(f"{private}/{NAME}", headers=recorded.owner)
        assert r.status_code == 200
        assert r.headers["content-type"] == "video/mp4"
        assert r.content[4:8] == b"ftyp"
        for who in ({}, recorded.stranger):
            assert client.get(private, headers=who).status_code == 404
            assert client.get(f"{private}/{NAME}", headers=who).status_code == 404
            [video] = client.get(public, headers=who).json()["videos"]
            assert video["seed"] == 0
            assert client.get(video["url"], headers=who).status_code == 200
        page = client.get(f"/submissions/{recorded.public_dev}").text
        assert f'src="{public}/{NAME}"' in page
        # A secret-seed phase's episodes are hidden scenes, the same for every entrant: none
        # is recorded, not even for its owner.
        for who in ({}, recorded.stranger, recorded.owner):
            assert client.get(secret, headers=who).json()["videos"] == []
            assert client.get(f"{secret}/{NAME}", headers=who).status_code == 404
        for name in ("..%2F..%2Fmanieval.db", "x.mp4", "nominal--PickCube-v1--ep1.mp4"):
            assert client.get(f"{private}/{name}", headers=recorded.owner).status_code == 404


def test_a_video_is_served_in_ranges_for_seeking(recorded: Recorded):
    url = f"{API}/submissions/{recorded.private_dev}/videos/{NAME}"
    with httpx.Client(base_url=recorded.url, timeout=60) as client:
        whole = client.get(url, headers=recorded.owner)
        part = client.get(url, headers=recorded.owner | {"Range": "bytes=100-199"})
    assert whole.headers["accept-ranges"] == "bytes"
    assert part.status_code == 206
    assert part.content == whole.content[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{len(whole.content)}"


def test_the_owner_plays_the_episode_on_the_submission_page(recorded: Recorded, artefacts: Path):
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(browser.new_context(viewport={"width": 1280, "height": 900})).new_page()
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))
        page.goto(f"{recorded.url}/login")
        page.get_by_label("Username or email").fill("alice")
        page.get_by_label("Password").fill(PASSWORD)
        page.get_by_role("button", name="Log in").click()
        page.goto(f"{recorded.url}/submissions/{recorded.private_dev}")
        method = page.locator("#method")
        expect(method).to_contain_text("Scripted grasp")
        for label in ("paper", "code"):
            link = method.get_by_role("link", name=label)
            expect(link).to_have_attribute("href", METHOD[f"{label}_url"])
            expect(link).to_have_attribute("rel", "noopener nofollow")
        section = page.get_by_role("region", name="Episode videos")
        expect(section).to_contain_text("PickCube-v1, nominal, episode 0")
        expect(section).to_contain_text("Seed")
        video = section.locator("video")
        expect(video).to_have_count(1)
        poster = f"/api/v1/submissions/{recorded.private_dev}/videos/{NAME}/poster"
        expect(video).to_have_attribute("poster", poster)
        # The rendered reset scene, not a black frame: what the page shows before play.
        shown = page.request.get(f"{recorded.url}{poster}")
        assert shown.status == 200
        assert shown.headers["content-type"] == "image/jpeg"
        image = Image.open(io.BytesIO(shown.body()))
        assert image.size == (512, 512)  # the task camera's own size (no video_size)
        assert np.asarray(image).std() > 10
        page.wait_for_function(
            "document.querySelector('.videos video').readyState >= 2", timeout=60_000
        )
        video.scroll_into_view_if_needed()
        page.screenshot(path=str(artefacts / "submission-videos.png"), full_page=True)
        browser.close()
    assert problems == []


def test_nothing_is_left_in_the_workers_recording_directory(recorded: Recorded):
    recording = recorded.data_dir / "recording"
    assert not recording.exists() or list(recording.iterdir()) == []
