"""Poster images of episode videos: the first frame (the scene after the reset) as a small JPEG,
so that a `<video>` shows the scene before it is played (iOS Safari loads no frame until then).

The evaluator writes each video's poster as it records it (``evaluator.video.write_poster``:
``<name>.poster.jpg`` beside the video, with the video's modification time); a Kubernetes Job
writes both straight into the video directory, and a worker uploads the poster after its video.
A video without one (recorded before posters were, or its poster lost) gets one made when it is
first asked for, where the server has ffmpeg, and kept the same way. It is written to a
temporary file and renamed, so concurrent first requests each leave a whole file. A video no
poster can be made of (corrupt, truncated, not an MP4) leaves an empty file there, so that it
is not decoded again and its page leaves the poster out. docs/videos.md.

Only videos `VideoStore.path` returned are decoded (regular files of a video's name inside the
video directory), and only when they are no larger than the store accepts and start as an MP4
does: the files Jobs write were never checked by the upload. ffmpeg reads that one local file
as MP4 (no other demuxer, no other protocol), one frame, on one thread, under a time limit, at
most two decodes at a time per server process.
"""

from __future__ import annotations

import logging
import os
import stat
import subprocess
import tempfile
import threading
from pathlib import Path

from evaluator.video import POSTER_MAX_BYTES, POSTER_MAX_SIDE, poster_name

MEDIA_TYPE = "image/jpeg"
DECODE_TIMEOUT_S = 10.0
_decoding = threading.BoundedSemaphore(2)
log = logging.getLogger(__name__)


def poster_file(video: Path) -> Path:
    """Where a video's poster is kept: beside it."""
    return video.with_name(poster_name(video.name))


def ffmpeg() -> str | None:
    """The ffmpeg that imageio-ffmpeg ships, or None where it is not installed."""
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    try:
        return str(imageio_ffmpeg.get_ffmpeg_exe())
    except RuntimeError:  # no binary for this platform
        return None


def has_poster(video: Path) -> bool:
    """Whether the video's poster is kept, or can be made here (ffmpeg, and no failed try)."""
    kept = _kept(video)
    if kept is not None:
        return 0 < kept.st_size <= POSTER_MAX_BYTES
    return ffmpeg() is not None


def poster(*, video: Path, max_bytes: int) -> Path | None:
    """The video's poster: the one kept (the evaluator's, or one made earlier), else made now
    and kept; None when none can be made."""
    if (kept := _kept(video)) is not None:
        return poster_file(video) if 0 < kept.st_size <= POSTER_MAX_BYTES else None
    if ffmpeg() is None:  # nothing to remember: the video may be fine
        return None
    if (kept := _kept(video)) is None:
        with _decoding:
            if (kept := _kept(video)) is None:  # not made while this request waited
                try:
                    made = video.stat().st_mtime_ns  # before decoding: a newer video is remade
                    data = _first_frame(video, max_bytes=max_bytes)
                    _write(poster_file(video), data, mtime_ns=made)
                except OSError as exc:  # a read-only or full volume: no poster, the video plays
                    log.warning("cannot keep the poster of %s: %s", video, exc)
                    return None
                kept = _kept(video)
    return poster_file(video) if kept is not None and kept.st_size > 0 else None


def _kept(video: Path) -> os.stat_result | None:
    """The kept poster's status (size 0: none can be made), or None when there is none up to
    date (missing, not a regular file: never follow a planted link, or not carrying the video's
    modification time: made of an earlier video of that name; the time is copied, not
    compared, since pods on other machines write the videos by their own clocks)."""
    try:
        kept, made = poster_file(video).lstat(), video.stat()
    except OSError:
        return None
    if not stat.S_ISREG(kept.st_mode) or kept.st_mtime_ns != made.st_mtime_ns:
        return None
    return kept


def _first_frame(video: Path, *, max_bytes: int) -> bytes:
    """The video's first frame as JPEG, at most POSTER_MAX_SIDE a side; empty when it cannot
    be read."""
    exe = ffmpeg()
    try:
        with video.open("rb") as f:
            head = f.read(8)
            size = os.fstat(f.fileno()).st_size
    except OSError:
        return b""
    if exe is None or size > max_bytes or head[4:8] != b"ftyp":
        return b""
    side = POSTER_MAX_SIDE
    scale = f"scale='min({side},iw)':'min({side},ih)':force_original_aspect_ratio=decrease"
    command = [
        exe, "-nostdin", "-hide_banner", "-loglevel", "error", "-threads", "1",
        "-protocol_whitelist", "file", "-f", "mp4", "-i", f"file:{video}",
        "-map", "0:v:0", "-frames:v", "1", "-vf", f"{scale},format=yuvj420p",
        "-c:v", "mjpeg", "-q:v", "4", "-f", "image2pipe", "pipe:1",
    ]  # fmt: skip
    try:
        done = subprocess.run(command, capture_output=True, timeout=DECODE_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        log.warning("no poster for %s: %s", video, exc)
        return b""
    out = done.stdout
    if done.returncode != 0 or not out.startswith(b"\xff\xd8") or len(out) > POSTER_MAX_BYTES:
        log.warning("no poster for %s: %s", video, done.stderr[-500:].decode(errors="replace"))
        return b""
    return out


def _write(path: Path, data: bytes, *, mtime_ns: int) -> None:
    """Write `path` whole or not at all (a temporary file beside it, then a rename), modified
    at `mtime_ns`."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.utime(tmp, ns=(mtime_ns, mtime_ns))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
