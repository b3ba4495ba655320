"""Episode videos: the frames of one episode as an MP4 every browser plays.

H.264 in yuv420p (the only chroma layout browsers decode), with the index at the front of the
file (`+faststart`) so that a `<video>` element can start and seek before the whole file has
arrived. The first frame is the reset state, then one after every k-th step (k from the suite's
`video_fps`, 1 without it) and one after the last.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from evaluator.plan import TaskRun
from evaluator.results import Video

VIDEO_NAME = re.compile(r"^[a-z0-9_\-]{1,100}--[A-Za-z0-9_\-]{1,100}-v\d{1,6}--ep\d{1,6}\.mp4\Z")
"""What a video's file name looks like: derived from its run, never from input."""
FFMPEG_OPTIONS = ("-movflags", "+faststart", "-preset", "veryfast")
POSTER_MAX_SIDE = 512  # pixels: pages show videos about 300 wide; a poster need not be larger
POSTER_MAX_BYTES = 1024 * 1024
"""The most a poster may weigh: larger is not one the evaluator made (a 512-pixel JPEG is
tens of kilobytes)."""


def poster_name(video: str) -> str:
    """The file name of a video's poster, kept beside it."""
    return video.removesuffix(".mp4") + ".poster.jpg"


def video_name(*, condition: str, env_id: str, episode: int) -> str:
    """The file name of a task run's episode video (ValueError if the parts are not names)."""
    name = f"{condition}--{env_id}--ep{episode}.mp4"
    if not VIDEO_NAME.match(name):
        raise ValueError(f"no video name for {condition!r}, {env_id!r}, episode {episode}")
    return name


def write_video(
    frames: list[Any], directory: Path, *, run: TaskRun, episode: int, fps: float
) -> Video:
    """Encode `frames` (H x W x 3 uint8), played at `fps`, to `<directory>/<video_name(...)>`."""
    import imageio.v2 as imageio

    directory.mkdir(parents=True, exist_ok=True)
    name = video_name(condition=run.condition.name, env_id=run.env_id, episode=episode)
    path = directory / name
    tmp = path.with_suffix(".part.mp4")
    writer: Any = imageio.get_writer(
        tmp,
        fps=fps,
        codec="libx264",
        quality=6,
        pixelformat="yuv420p",
        macro_block_size=16,
        ffmpeg_params=list(FFMPEG_OPTIONS),
    )
    with writer:
        for frame in frames:
            writer.append_data(np.asarray(frame, dtype=np.uint8))
    tmp.replace(path)  # whoever lists the directory never sees half a file
    if frames:
        write_poster(frames[0], path)
    return Video(env_id=run.env_id, condition=run.condition.name, episode=episode, path=str(path))


def write_poster(frame: Any, video: Path) -> Path:
    """The video's first frame (the scene after the reset) as a JPEG of at most
    POSTER_MAX_SIDE a side, beside it and carrying its modification time: what the server
    takes for the video's poster (a `<video>` shows it before it is played; iOS Safari shows
    no frame until then). Written here, where the frames are, so that no server needs a
    video decoder to show it (docs/videos.md)."""
    from PIL import Image

    image = Image.fromarray(np.asarray(frame, dtype=np.uint8))
    image.thumbnail((POSTER_MAX_SIDE, POSTER_MAX_SIDE))
    poster = video.with_name(poster_name(video.name))
    tmp = poster.with_suffix(".part")
    image.save(tmp, format="JPEG", quality=85)
    made = video.stat()
    os.utime(tmp, ns=(made.st_atime_ns, made.st_mtime_ns))
    tmp.replace(poster)
    return poster
