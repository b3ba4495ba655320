"""Storing episode videos through ``/internal/v1``: only a running attempt's, only MP4s named as
the evaluator names them, bounded in size and number; a re-run's replace the earlier ones."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from evaluator.video import POSTER_MAX_BYTES, poster_name
from internal_api.schemas import State
from server.kit.errors import Invalid
from server.kit.settings import Settings
from server.submissions.video_store import NotAVideo, VideoStore, VideoTooLarge
from testkit.factories import RecordingQueue, make_challenge, make_user, queue_submission
from testkit.workers import server_api, server_app, worker_settings
from worker.outcome import ended
from worker.server_api import ServerAPI

NAME = "nominal--PickCube-v1--ep0.mp4"
MP4 = b"\x00\x00\x00\x18ftypisom" + b"\x00" * 1000  # what an ISO media file starts with
URL = "/internal/v1/submissions/{sid}/attempts/{attempt}/videos/{name}"


@pytest.fixture
def small_settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"max_video_bytes": 64 * 1024, "max_videos_per_attempt": 2})


@pytest.fixture
def app(
    small_settings: Settings, committed_sessions: sessionmaker[Session], work: RecordingQueue
) -> FastAPI:
    return server_app(small_settings, committed_sessions, work)


@pytest.fixture
def api(app: FastAPI, small_settings: Settings) -> Iterator[ServerAPI]:
    client = server_api(app, worker_settings(small_settings))
    yield client
    client.close()


@pytest.fixture
def http(app: FastAPI, small_settings: Settings) -> Iterator[TestClient]:
    token = small_settings.secret("worker_token")
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "video/mp4"}
    with TestClient(app, base_url="http://testserver", headers=headers) as client:
        yield client


@pytest.fixture
def running(committed_sessions: sessionmaker[Session], api: ServerAPI) -> int:
    """A submission whose first attempt a worker claimed and runs."""
    with committed_sessions() as db:
        challenge = make_challenge(db, quota_concurrent=10, quota_per_day=10)
        sid = queue_submission(db, make_user(db, "alice"), challenge).id
        db.commit()
    assert api.claim("w1") is not None
    assert api.running(sid, 1, reason="evaluating", deadline_s=600) is not None
    return sid


def stored(settings: Settings, sid: int, attempt: int = 1) -> list[str]:
    directory = settings.data_dir / "videos" / str(sid) / str(attempt)
    return sorted(p.name for p in directory.iterdir()) if directory.is_dir() else []


def test_a_running_attempts_video_is_kept_under_the_data_directory(
    api: ServerAPI, running: int, small_settings: Settings, tmp_path: Path
):
    video = tmp_path / NAME
    video.write_bytes(MP4)
    assert api.upload_video(running, 1, video) is True
    assert stored(small_settings, running) == [NAME]
    path = small_settings.data_dir / "videos" / str(running) / "1" / NAME
    assert path.read_bytes() == MP4
    assert api.upload_video(running, 1, video) is True  # a repeat replaces it


@pytest.mark.parametrize(
    ("name", "headers", "body", "status"),
    [
        ("evil.sh", {}, MP4, 422),
        ("nominal--PickCube-v1--ep0.mp4.part", {}, MP4, 422),
        ("..%2Fnominal--PickCube-v1--ep0.mp4", {}, MP4, 404),  # never a route, let alone a path
        (NAME, {"Content-Type": "application/octet-stream"}, MP4, 415),
        (NAME, {}, b"#!/bin/sh\n" + b"x" * 100, 415),
        (NAME, {}, MP4 + b"\x00" * 64 * 1024, 413),
        (NAME, {"Authorization": "Bearer not-the-worker-token"}, MP4, 401),
    ],
)
def test_uploads_that_are_not_a_bounded_mp4_of_an_expected_name_are_refused(
    http: TestClient,
    running: int,
    small_settings: Settings,
    name: str,
    headers: dict[str, str],
    body: bytes,
    status: int,
):
    r = http.put(URL.format(sid=running, attempt=1, name=name), content=body, headers=headers)
    assert r.status_code == status, r.text
    assert stored(small_settings, running) == []


def test_an_attempt_stores_only_so_many_videos(http: TestClient, running: int):
    for episode, status in ((0, 204), (1, 204), (2, 413)):
        name = f"nominal--PickCube-v1--ep{episode}.mp4"
        r = http.put(URL.format(sid=running, attempt=1, name=name), content=MP4)
        assert r.status_code == status, r.text


def test_videos_are_refused_for_attempts_that_do_not_run(
    http: TestClient, api: ServerAPI, running: int, small_settings: Settings, tmp_path: Path
):
    assert http.put(URL.format(sid=running, attempt=2, name=NAME), content=MP4).status_code == 409
    assert http.put(URL.format(sid=999, attempt=1, name=NAME), content=MP4).status_code == 404
    assert api.final(running, 1, ended(State.ERROR, "ended")) == State.ERROR
    video = tmp_path / NAME
    video.write_bytes(MP4)
    assert api.upload_video(running, 1, video) is False  # the attempt has ended
    assert stored(small_settings, running) == []


def test_a_new_attempts_videos_replace_the_earlier_attempts(tmp_path: Path):
    store = VideoStore(tmp_path, max_bytes=1 << 20, max_per_attempt=10)
    store.store(submission_id=3, attempt=1, name=NAME, data=MP4)
    assert store.path(submission_id=3, attempt=1, name=NAME) is not None
    store.store(submission_id=3, attempt=2, name=NAME, data=MP4)
    assert store.path(submission_id=3, attempt=1, name=NAME) is None
    assert [p.name for p in (tmp_path / "3").iterdir()] == ["2"]
    assert store.path(submission_id=3, attempt=2, name="../2/" + NAME) is None


def test_the_store_checks_what_it_keeps(tmp_path: Path):
    store = VideoStore(tmp_path, max_bytes=2000, max_per_attempt=10)
    with pytest.raises(Invalid):
        store.store(submission_id=1, attempt=1, name="../x.mp4", data=MP4)
    with pytest.raises(VideoTooLarge):
        store.store(submission_id=1, attempt=1, name=NAME, data=MP4 * 2)
    with pytest.raises(NotAVideo):
        store.store(submission_id=1, attempt=1, name=NAME, data=b"x" * 100)
    assert not (tmp_path / "1").exists()


def test_a_link_planted_in_the_video_directory_serves_nothing(tmp_path: Path):
    # On Kubernetes evaluation pods write into this directory: a link there must not serve a
    # file from elsewhere, not even under a video's name.
    store = VideoStore(tmp_path / "videos", max_bytes=1 << 20, max_per_attempt=10)
    secret = tmp_path / "signing-key.pem"
    secret.write_text("-----BEGIN PRIVATE KEY-----")
    attempt = store.attempt_dir(submission_id=5, attempt=1)
    attempt.mkdir(parents=True)
    (attempt / NAME).symlink_to(secret)
    assert store.path(submission_id=5, attempt=1, name=NAME) is None
    assert store.path(submission_id=5, attempt=1, name=NAME + "\n") is None


def test_a_secret_seed_phase_records_no_video(db: Session):
    from server.submissions.states import transition
    from server.submissions.work import assignment

    challenge = make_challenge(db, quota_concurrent=2)
    challenge.suite_yaml += "\nvideos: 1\n"  # the suite asks for videos in every phase
    user = make_user(db, "ada")
    made = {
        phase: queue_submission(db, user, challenge, phase=phase).id for phase in ("dev", "test")
    }
    db.commit()
    for phase, recorded in (("dev", 1), ("test", 0)):
        assert transition(db, made[phase], 1, State.LAUNCHING, "starting")
        db.commit()
        plan = assignment(db, submission_id=made[phase], attempt=1, seed_secret=b"k" * 32).plan
        assert plan.videos == recorded, phase


JPEG = b"\xff\xd8\xff\xe0" + b"\x00" * 100


def test_a_videos_poster_is_kept_beside_it_with_its_time(
    api: ServerAPI, running: int, small_settings: Settings, tmp_path: Path
):
    video, poster = tmp_path / NAME, tmp_path / poster_name(NAME)
    video.write_bytes(MP4)
    poster.write_bytes(JPEG)
    assert api.upload_video(running, 1, video) is True
    assert api.upload_poster(running, 1, video, poster) is True
    assert stored(small_settings, running) == [NAME, poster_name(NAME)]
    directory = small_settings.data_dir / "videos" / str(running) / "1"
    assert (directory / poster_name(NAME)).read_bytes() == JPEG
    made = (directory / NAME).stat().st_mtime_ns
    assert (directory / poster_name(NAME)).stat().st_mtime_ns == made  # what makes it its poster


@pytest.mark.parametrize(
    ("video_first", "headers", "body", "status"),
    [
        (False, {}, JPEG, 422),  # no video to give it to
        (True, {"Content-Type": "video/mp4"}, JPEG, 415),
        (True, {}, b"<svg onload=alert(1)>", 415),
        (True, {}, JPEG + b"\x00" * POSTER_MAX_BYTES, 413),
    ],
    ids=["before-its-video", "wrong-type", "not-a-jpeg", "too-large"],
)
def test_posters_that_are_not_a_bounded_jpeg_of_a_stored_video_are_refused(
    http: TestClient,
    running: int,
    small_settings: Settings,
    video_first: bool,
    headers: dict[str, str],
    body: bytes,
    status: int,
):
    url = URL.format(sid=running, attempt=1, name=NAME)
    if video_first:
        assert http.put(url, content=MP4).status_code == 204
    r = http.put(f"{url}/poster", content=body, headers={"Content-Type": "image/jpeg"} | headers)
    assert r.status_code == status, r.text
    assert poster_name(NAME) not in stored(small_settings, running)


def test_posters_are_refused_once_the_attempt_ended(
    api: ServerAPI, running: int, small_settings: Settings, tmp_path: Path
):
    video, poster = tmp_path / NAME, tmp_path / poster_name(NAME)
    video.write_bytes(MP4)
    poster.write_bytes(JPEG)
    assert api.upload_video(running, 1, video) is True
    assert api.final(running, 1, ended(State.ERROR, "ended")) == State.ERROR
    assert api.upload_poster(running, 1, video, poster) is False
    assert stored(small_settings, running) == [NAME]
