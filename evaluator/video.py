"""Episode videos: the frames of one episode as an MP4 every browser plays.

H.264 in yuv420p (the only chroma layout browsers decode), with the index at the front of the
file (`+faststart`) so that a `<video>` element can start and seek before the whole file has
arrived. The first frame is the reset state, then one after every k-th step (k from the suite's
`video_fps`, 1 without it) and one after the last.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from evaluator.plan import TaskRun
from evaluator.results import Video

VIDEO_NAME = re.compile(r"^[a-z0-9_\-]{1,100}--[A-Za-z0-9_\-]{1,100}-v\d{1,6}--ep\d{1,6}\.mp4\Z")
"""What a video's file name looks like: derived from its run, never from input."""
FFMPEG_OPTIONS = ("-movflags", "+faststart", "-preset", "veryfast")


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
    return Video(env_id=run.env_id, condition=run.condition.name, episode=episode, path=str(path))
