"""Episode videos and trajectories of an attempt: recorded by the evaluator into a directory
the worker owns, then uploaded to the server through ``/internal/v1`` (docs/videos.md,
docs/trajectories.md).

The directory is private to this worker (mode 0700, under its data directory) and never given to
the policy: a `local:` policy runs in its own process with no word of it, a container gets no
mount of it. Only files named as the evaluator names them are sent; the server checks names,
sizes and content again.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from evaluator.results import EvaluationResult
from evaluator.trajectory import TRAJECTORY_NAME, trajectory_stem
from evaluator.video import VIDEO_NAME, poster_name, video_name
from worker.server_api import ServerAPI, ServerUnavailable, WorkerRefused
from worker.settings import WorkerSettings

log = logging.getLogger(__name__)


@contextmanager
def recording_dir(settings: WorkerSettings, *, submission_id: int, attempt: int) -> Iterator[Path]:
    """A fresh private directory for one attempt's videos, removed when the attempt ends."""
    parent = settings.data_dir / "recording"
    parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    directory = Path(tempfile.mkdtemp(prefix=f"{submission_id}-{attempt}-", dir=parent))
    try:
        yield directory
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def upload_videos(
    api: ServerAPI, *, submission_id: int, attempt: int, result: EvaluationResult, directory: Path
) -> EvaluationResult:
    """Send the result's videos to the server; the result, its videos named by file name only
    (the worker's paths mean nothing elsewhere). A video that cannot be sent is logged and
    left out, and so are the rest: the server is failing to store them, and the result, which
    does not depend on them, must not wait (no heartbeat goes out meanwhile)."""
    sent = []
    for video in result.videos:
        name = video_name(condition=video.condition, env_id=video.env_id, episode=video.episode)
        path = directory / name
        if not VIDEO_NAME.match(name) or path.is_symlink() or not path.is_file():
            continue
        if api.stop.is_set():
            break
        poster = directory / poster_name(name)
        try:
            if not api.upload_video(submission_id, attempt, path):
                break  # the attempt is no longer current: neither are its videos
            if poster.is_file() and not poster.is_symlink():
                if not api.upload_poster(submission_id, attempt, path, poster):
                    break
        except (ServerUnavailable, WorkerRefused, RuntimeError, OSError) as exc:
            log.warning(
                "videos of submission %s not stored (from %s on): %s", submission_id, name, exc
            )
            break
        sent.append(video.model_copy(update={"path": name}))
    return result.model_copy(update={"videos": sent})


def upload_trajectories(
    api: ServerAPI, *, submission_id: int, attempt: int, result: EvaluationResult, directory: Path
) -> int:
    """Send the trajectory files of the result's task runs (`.json` after its `.h5`, so that a
    listed pair is whole); how many were sent. As with videos, the first that cannot be sent
    is logged and it and the rest are left out."""
    names = [
        trajectory_stem(condition=condition.name, env_id=task.env_id) + suffix
        for condition in result.conditions
        for task in condition.tasks
        for suffix in (".h5", ".json")
    ]
    sent = 0
    for name in names:
        path = directory / name
        if not TRAJECTORY_NAME.match(name) or path.is_symlink() or not path.is_file():
            continue
        if api.stop.is_set():
            break
        try:
            if not api.upload_trajectory(submission_id, attempt, path):
                break
        except (ServerUnavailable, WorkerRefused, RuntimeError, OSError) as exc:
            log.warning(
                "trajectories of submission %s not stored (from %s on): %s",
                submission_id,
                name,
                exc,
            )
            break
        sent += 1
    return sent
