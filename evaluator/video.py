"""Episode videos: the frames of one episode as a small H.264 mp4."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from evaluator.plan import TaskRun
from evaluator.results import Video


def write_video(
    frames: list[Any], directory: Path, *, run: TaskRun, episode: int, fps: int
) -> Video:
    """Encode `frames` (H x W x 3 uint8) to `<dir>/<condition>-<env_id>-ep<N>.mp4`."""
    import imageio.v2 as imageio

    directory.mkdir(parents=True, exist_ok=True)
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", f"{run.condition.name}-{run.env_id}-ep{episode}")
    path = directory / f"{safe}.mp4"
    writer: Any = imageio.get_writer(path, fps=fps, codec="libx264", quality=6, macro_block_size=8)
    with writer:
        for frame in frames:
            writer.append_data(np.asarray(frame, dtype=np.uint8))
    return Video(env_id=run.env_id, condition=run.condition.name, episode=episode, path=str(path))
