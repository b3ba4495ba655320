"""Posters of episode videos: the first frame of a real MP4 (encoded here as the evaluator
encodes), shown as the video is, made once and kept beside it, and left out of the page when
the video cannot be read."""

from __future__ import annotations

import io
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy.orm import Session

from evaluator.results import Video
from evaluator.video import FFMPEG_OPTIONS, POSTER_MAX_BYTES, write_poster
from server.kit.settings import Settings
from server.models import Challenge, Submission, User
from server.submissions import posters
from testkit.factories import make_user
from tests.web.helpers import browser, finished

NAME = "nominal--PickCube-v1--ep0.mp4"
FIRST, REST = 200, 30  # grey levels of the first frame and of the others
MAX_BYTES = 256 * 1024


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"max_video_bytes": MAX_BYTES})


@pytest.fixture
def people(client: TestClient, db: Session) -> dict[str, TestClient]:
    for name in ("alice", "bob"):
        make_user(db, name)
    make_user(db, "judge", admin=True)
    return {name: browser(client, name) for name in ("alice", "bob", "judge")} | {
        "anonymous": browser(client)
    }


@pytest.fixture
def decodes(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """The videos the server decodes a frame of, in order."""
    seen: list[Path] = []
    first_frame = posters._first_frame

    def counted(video: Path, *, max_bytes: int) -> bytes:
        seen.append(video)
        return first_frame(video, max_bytes=max_bytes)

    monkeypatch.setattr(posters, "_first_frame", counted)
    return seen


def encode(path: Path, *, width: int = 96, height: int = 64, frames: int = 6) -> Path:
    """A real H.264 MP4, as `evaluator.video.write_video` encodes: a bright first frame."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio.get_writer(
        path,
        fps=10,
        codec="libx264",
        pixelformat="yuv420p",
        macro_block_size=16,
        ffmpeg_params=list(FFMPEG_OPTIONS),
    )
    with writer:
        for i in range(frames):
            writer.append_data(np.full((height, width, 3), FIRST if i == 0 else REST, np.uint8))
    return path


def alices(db: Session, tiny: Challenge, *, public: bool = False) -> Submission:
    alice = db.query(User).filter_by(username="alice").one()
    video = Video(env_id="PickCube-v1", condition="nominal", episode=0, path="/unused")
    return finished(db, alice, tiny, [True, False], videos=[video], public=public)


def stored(settings: Settings, s: Submission, name: str = NAME) -> Path:
    return settings.resolved_video_dir / str(s.id) / str(s.attempt) / name


def poster_url(s: Submission, name: str = NAME) -> str:
    return f"/api/v1/submissions/{s.id}/videos/{name}/poster"


def test_a_poster_is_the_videos_first_frame_as_a_jpeg_of_its_size(
    db: Session, tiny: Challenge, people: dict[str, TestClient], settings: Settings
) -> None:
    s = alices(db, tiny)
    encode(stored(settings, s))
    r = people["alice"].get(poster_url(s))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/jpeg"
    assert r.headers["cache-control"] == "private"
    image = Image.open(io.BytesIO(r.content))
    assert (image.format, image.size) == ("JPEG", (96, 64))
    assert abs(float(np.asarray(image).mean()) - FIRST) < 8  # the first frame, not a later one


def test_a_large_video_gets_a_poster_at_most_512_pixels_a_side_of_its_shape(
    db: Session, tiny: Challenge, people: dict[str, TestClient], settings: Settings
) -> None:
    s = alices(db, tiny)
    encode(stored(settings, s), width=1024, height=512, frames=2)
    r = people["alice"].get(poster_url(s))
    assert r.status_code == 200, r.text
    assert Image.open(io.BytesIO(r.content)).size == (512, 256)


def test_a_poster_is_shown_to_whoever_sees_the_video_and_404_to_anyone_else(
    db: Session, tiny: Challenge, people: dict[str, TestClient], settings: Settings
) -> None:
    s = alices(db, tiny)
    encode(stored(settings, s))
    for who in ("alice", "judge"):
        assert people[who].get(poster_url(s)).status_code == 200
    for who in ("bob", "anonymous"):
        assert people[who].get(poster_url(s)).status_code == 404
        assert people[who].get(poster_url(s).removesuffix("/poster")).status_code == 404
    s.public = True
    db.commit()
    for who in ("bob", "anonymous"):
        assert people[who].get(poster_url(s)).status_code == 200


def test_no_poster_for_a_video_that_is_not_stored_or_not_listed(
    db: Session, tiny: Challenge, people: dict[str, TestClient], settings: Settings
) -> None:
    s = alices(db, tiny)  # lists episode 0 only, stores nothing yet
    r = people["alice"].get(poster_url(s))
    assert r.status_code == 404
    assert NAME in r.json()["error"]["message"]
    encode(stored(settings, s, "nominal--PickCube-v1--ep1.mp4"))  # stored, never listed
    assert people["alice"].get(poster_url(s, "nominal--PickCube-v1--ep1.mp4")).status_code == 404
    assert people["alice"].get(poster_url(s, "..%2F..%2Fmanieval.db")).status_code == 404


def test_a_poster_is_made_once_kept_beside_the_video_and_remade_for_a_new_video(
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    settings: Settings,
    decodes: list[Path],
) -> None:
    s = alices(db, tiny)
    video = encode(stored(settings, s))
    first = people["alice"].get(poster_url(s)).content
    kept = video.with_name("nominal--PickCube-v1--ep0.poster.jpg")
    assert kept.read_bytes() == first
    made = kept.stat().st_mtime_ns
    assert people["bob"].get(poster_url(s)).status_code == 404  # no decoding for a stranger
    assert people["judge"].get(poster_url(s)).content == first
    assert decodes == [video]
    assert kept.stat().st_mtime_ns == made
    assert sorted(p.name for p in video.parent.iterdir()) == [NAME, kept.name]  # no temp file
    assert made == video.stat().st_mtime_ns  # the video's own, whatever the clocks say
    encode(video, width=64, height=64)  # the video replaced: its old poster no longer fits
    earlier = made - 3_600_000_000_000  # written by a pod whose clock is an hour behind
    os.utime(video, ns=(earlier, earlier))
    r = people["alice"].get(poster_url(s))
    assert r.status_code == 200, r.text
    assert Image.open(io.BytesIO(r.content)).size == (64, 64)
    assert people["alice"].get(poster_url(s)).status_code == 200
    assert decodes == [video, video]


def test_concurrent_first_requests_leave_one_whole_poster(settings: Settings) -> None:
    video = encode(settings.resolved_video_dir / "1" / "1" / NAME)
    with ThreadPoolExecutor(max_workers=8) as pool:
        made = list(pool.map(lambda _: posters.poster(video=video, max_bytes=MAX_BYTES), range(8)))
    assert made == [posters.poster_file(video)] * 8
    assert Image.open(made[0]).size == (96, 64)
    assert sorted(p.name for p in video.parent.iterdir()) == [NAME, made[0].name]


def test_the_page_gives_each_video_its_poster(
    db: Session, tiny: Challenge, people: dict[str, TestClient], settings: Settings
) -> None:
    s = alices(db, tiny, public=True)
    encode(stored(settings, s))
    url = poster_url(s)
    for who in ("alice", "anonymous"):
        html = people[who].get(f"/submissions/{s.id}").text
        assert f'src="{url.removesuffix("/poster")}" poster="{url}"' in html
    [listed] = people["anonymous"].get(f"/api/v1/submissions/{s.id}/videos").json()["videos"]
    assert listed["poster"] == url


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda data: data[: len(data) // 2], id="truncated"),
        pytest.param(lambda data: data[:8] + b"\x00" * 2000, id="garbage-after-ftyp"),
        pytest.param(lambda data: b"#EXTM3U\nhttp://127.0.0.1:9/x.ts\n", id="not-an-mp4"),
        pytest.param(lambda data: data + b"\x00" * MAX_BYTES, id="larger-than-the-store-takes"),
    ],
)
def test_a_video_no_poster_can_be_made_of_is_tried_once_and_its_page_leaves_the_poster_out(
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    settings: Settings,
    decodes: list[Path],
    damage: object,
) -> None:
    s = alices(db, tiny)
    video = encode(stored(settings, s))
    video.write_bytes(damage(video.read_bytes()))  # type: ignore[operator]
    page = f"/submissions/{s.id}"
    assert 'poster="' in people["alice"].get(page).text  # not known yet: no decoding for a page
    assert decodes == []
    for _ in range(2):
        r = people["alice"].get(poster_url(s))
        assert r.status_code == 404
        assert "no poster" in r.json()["error"]["message"]
    assert decodes == [video]  # tried once, remembered
    assert 'poster="' not in people["alice"].get(page).text
    assert people["alice"].get(poster_url(s).removesuffix("/poster")).status_code == 200
    [listed] = people["alice"].get(f"/api/v1/submissions/{s.id}/videos").json()["videos"]
    assert listed["poster"] is None


def test_only_regular_files_the_store_holds_are_decoded_and_served(
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    settings: Settings,
    tmp_path: Path,
    decodes: list[Path],
) -> None:
    s = alices(db, tiny)
    elsewhere = encode(tmp_path / "elsewhere" / NAME)
    video = stored(settings, s)
    video.parent.mkdir(parents=True)
    video.symlink_to(elsewhere)  # planted by a pod writing into the video directory
    assert people["alice"].get(poster_url(s)).status_code == 404
    assert decodes == []
    video.unlink()
    encode(video)
    kept = posters.poster_file(video)
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the web")
    kept.symlink_to(secret)  # a planted poster is never followed: it is made over
    r = people["alice"].get(poster_url(s))
    assert r.status_code == 200
    assert r.content.startswith(b"\xff\xd8")
    assert not kept.is_symlink()
    assert secret.read_text() == "not for the web"


def test_without_ffmpeg_the_page_has_no_posters_and_the_video_still_plays(
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    settings: Settings,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(posters, "ffmpeg", lambda: None)  # as in an image without imageio-ffmpeg
    s = alices(db, tiny)
    encode(stored(settings, s))
    assert 'poster="' not in people["alice"].get(f"/submissions/{s.id}").text
    assert people["alice"].get(poster_url(s)).status_code == 404
    assert people["alice"].get(poster_url(s).removesuffix("/poster")).status_code == 200


def test_the_poster_the_evaluator_kept_is_served_where_the_server_has_no_ffmpeg(
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    settings: Settings,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A Kubernetes Job writes the video and its poster into the store; a control-plane image
    has no decoder, and needs none."""
    monkeypatch.setattr(posters, "ffmpeg", lambda: None)
    s = alices(db, tiny)
    video = encode(stored(settings, s))
    kept = write_poster(np.full((64, 96, 3), FIRST, np.uint8), video)
    assert f'poster="{poster_url(s)}"' in people["alice"].get(f"/submissions/{s.id}").text
    r = people["alice"].get(poster_url(s))
    assert r.status_code == 200
    assert r.headers["content-type"] == posters.MEDIA_TYPE
    assert r.content == kept.read_bytes()


def test_a_kept_poster_of_another_video_or_too_large_is_not_served(
    db: Session,
    tiny: Challenge,
    people: dict[str, TestClient],
    settings: Settings,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(posters, "ffmpeg", lambda: None)
    s = alices(db, tiny)
    video = encode(stored(settings, s))
    kept = write_poster(np.full((64, 96, 3), FIRST, np.uint8), video)
    made = video.stat().st_mtime_ns
    os.utime(kept, ns=(made, made - 10**9))  # an earlier video's poster of that name
    assert people["alice"].get(poster_url(s)).status_code == 404
    kept.write_bytes(b"\xff\xd8\xff" + b"\x00" * POSTER_MAX_BYTES)  # no poster weighs that
    os.utime(kept, ns=(made, made))
    assert 'poster="' not in people["alice"].get(f"/submissions/{s.id}").text
    assert people["alice"].get(poster_url(s)).status_code == 404
