"""Episode video files on the server: ``<video_dir>/<submission>/<attempt>/<name>.mp4``, and
beside them the attempt's trajectories, ``.../<attempt>/trajectories/<condition>--<Task>.h5``
(+ ``.json``, docs/trajectories.md).

Workers upload them through ``/internal/v1`` (`store_video`); on Kubernetes the evaluation
Jobs write them into the same layout on a shared volume. A file's name is the one the
evaluator gives it (`evaluator.video.video_name`): it is checked against that pattern, never
used as a path of its own, and a submission's videos are only ever looked up by names
computed from its result document. Only the current attempt's directory is read; storing a
video of an attempt removes those of its earlier attempts (a re-run replaces them).
"""

from __future__ import annotations

import json
import os
import shutil
import stat
from dataclasses import dataclass
from pathlib import Path

from evaluator.trajectory import TRAJECTORY_NAME
from evaluator.video import POSTER_MAX_BYTES, VIDEO_NAME, poster_name
from server.kit.errors import AppError, Invalid

MEDIA_TYPE = "video/mp4"
POSTER_MEDIA_TYPE = "image/jpeg"
TRAJECTORIES = "trajectories"
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
TRAJECTORY_MEDIA_TYPES = {".h5": "application/x-hdf5", ".json": "application/json"}


class VideoTooLarge(AppError):
    status = 413
    code = "too_large"


class NotAVideo(AppError):
    status = 415
    code = "unsupported_media_type"


class NotATrajectory(AppError):
    status = 415
    code = "unsupported_media_type"


@dataclass(frozen=True)
class VideoStore:
    """The video directory of one server, and what it accepts."""

    root: Path
    max_bytes: int
    max_per_attempt: int
    max_trajectory_bytes: int = 64 * 1024**2

    def attempt_dir(self, *, submission_id: int, attempt: int) -> Path:
        """Where an attempt's videos are (both ids are integers: no name from input)."""
        return self.root / str(int(submission_id)) / str(int(attempt))

    def path(self, *, submission_id: int, attempt: int, name: str) -> Path | None:
        """The stored file of that name, or None (also for a name that is not a video's, and
        for a link: on Kubernetes the evaluation pods write into this directory, and a link
        planted there must not serve a file from elsewhere)."""
        if not VIDEO_NAME.fullmatch(name):
            return None
        return self._regular(self.attempt_dir(submission_id=submission_id, attempt=attempt) / name)

    def trajectory_path(self, *, submission_id: int, attempt: int, name: str) -> Path | None:
        """The stored trajectory file of that name, or None (as `path` for videos)."""
        if not TRAJECTORY_NAME.fullmatch(name):
            return None
        directory = self.attempt_dir(submission_id=submission_id, attempt=attempt) / TRAJECTORIES
        return self._regular(directory / name)

    def _regular(self, path: Path) -> Path | None:
        """`path` if it is a regular file (not a link) inside the store, else None."""
        try:
            mode = path.lstat().st_mode
        except OSError:
            return None
        if not stat.S_ISREG(mode) or not path.resolve().is_relative_to(self.root.resolve()):
            return None
        return path

    def store(self, *, submission_id: int, attempt: int, name: str, data: bytes) -> None:
        """Keep one uploaded video, replacing a file of the same name; Invalid, VideoTooLarge
        or NotAVideo when the upload is not one."""
        if not VIDEO_NAME.fullmatch(name):
            raise Invalid(f"{name!r} is not a video name (condition--Task-vN--epK.mp4)")
        if len(data) > self.max_bytes:
            raise VideoTooLarge(f"the video has {len(data)} bytes, at most {self.max_bytes}")
        if data[4:8] != b"ftyp":  # an ISO media file starts with its `ftyp` box
            raise NotAVideo("the upload is not an MP4 file")
        directory = self.attempt_dir(submission_id=submission_id, attempt=attempt)
        self._remove_other_attempts(submission_id=submission_id, attempt=attempt)
        directory.mkdir(parents=True, exist_ok=True)
        final = directory / name
        stored = [p for p in directory.iterdir() if p.name != name and p.suffix == ".mp4"]
        if not final.exists() and len(stored) >= self.max_per_attempt:
            raise VideoTooLarge(f"an attempt may store at most {self.max_per_attempt} videos")
        _write(directory, name, data)

    def store_poster(self, *, submission_id: int, attempt: int, name: str, data: bytes) -> None:
        """Keep the poster of the stored video `name`, carrying the video's modification time
        (what makes it that video's: `posters`); Invalid (no such video: the video is sent
        first), VideoTooLarge or NotAVideo when the upload is not a JPEG."""
        if not VIDEO_NAME.fullmatch(name):
            raise Invalid(f"{name!r} is not a video name (condition--Task-vN--epK.mp4)")
        if len(data) > POSTER_MAX_BYTES:
            raise VideoTooLarge(f"the poster has {len(data)} bytes, at most {POSTER_MAX_BYTES}")
        if not data.startswith(b"\xff\xd8\xff"):  # a JPEG starts with SOI and a marker
            raise NotAVideo("the upload is not a JPEG image")
        video = self.path(submission_id=submission_id, attempt=attempt, name=name)
        if video is None:
            raise Invalid(f"no video {name} of this attempt is stored: send the video first")
        _write(video.parent, poster_name(name), data)
        made = video.stat()
        os.utime(video.parent / poster_name(name), ns=(made.st_atime_ns, made.st_mtime_ns))

    def store_trajectory(self, *, submission_id: int, attempt: int, name: str, data: bytes) -> None:
        """Keep one uploaded trajectory file (a task run's `.h5` or `.json`), replacing one of
        the same name; Invalid, VideoTooLarge or NotATrajectory when the upload is not one."""
        if not TRAJECTORY_NAME.fullmatch(name):
            raise Invalid(f"{name!r} is not a trajectory name (condition--Task-vN.h5 or .json)")
        if len(data) > self.max_trajectory_bytes:
            raise VideoTooLarge(
                f"the trajectory file has {len(data)} bytes, at most {self.max_trajectory_bytes}"
            )
        if name.endswith(".h5") and not data.startswith(HDF5_SIGNATURE):
            raise NotATrajectory("the upload is not an HDF5 file")
        if name.endswith(".json") and not _is_trajectory_json(data):
            raise NotATrajectory("the upload is not a ManiSkill trajectory's JSON")
        self._remove_other_attempts(submission_id=submission_id, attempt=attempt)
        directory = self.attempt_dir(submission_id=submission_id, attempt=attempt) / TRAJECTORIES
        directory.mkdir(parents=True, exist_ok=True)
        _write(directory, name, data)

    def _remove_other_attempts(self, *, submission_id: int, attempt: int) -> None:
        parent = self.root / str(int(submission_id))
        if not parent.is_dir():
            return
        for child in parent.iterdir():
            if child.name != str(attempt):
                shutil.rmtree(child, ignore_errors=True)


def _write(directory: Path, name: str, data: bytes) -> None:
    """Write `directory/name` whole or not at all (readers never see half a file)."""
    tmp = directory / f"{name}.part"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, directory / name)


def _is_trajectory_json(data: bytes) -> bool:
    """Whether `data` is a JSON object with ManiSkill's `env_info` and `episodes`."""
    try:
        document = json.loads(data)
    except ValueError:
        return False
    return isinstance(document, dict) and {"env_info", "episodes"} <= document.keys()
