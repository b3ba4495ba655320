"""Episode videos of a submission's current attempt: listed and served to whoever may see the
submission (its owner and administrators always, everyone when it is public), with each
episode's seed (null in secret-seed phases), success and steps. docs/videos.md.
"""

from __future__ import annotations

from pathlib import Path as FilePath
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field, ValidationError
from sqlalchemy.orm import Session

from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.video import video_name
from server.accounts.deps import CallerDep
from server.kit.deps import DBDep, Id
from server.kit.errors import ERROR_RESPONSES, NotFound
from server.kit.settings import Settings
from server.models import Submission, User
from server.submissions import posters
from server.submissions.deps import services
from server.submissions.service import get_visible
from server.submissions.video_store import MEDIA_TYPE, VideoStore

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)
VideoName = Annotated[str, Path(min_length=1, max_length=300)]


class VideoOut(BaseModel):
    """One recorded episode of the submission's current attempt."""

    condition: str
    env_id: str
    episode: int = Field(description="the episode's index in its task run")
    seed: int | None = Field(description="null in phases whose seeds are secret")
    success_once: bool
    success_at_end: bool | None
    steps: int
    failure: str | None
    url: str = Field(description="the MP4 (H.264), with the same access rules; Range supported")
    poster: str | None = Field(
        description="a JPEG of its first frame, with the same access rules; null when the video "
        "is known to be unreadable or the server has no ffmpeg"
    )


class VideosOut(BaseModel):
    submission_id: int
    attempt: int
    videos: list[VideoOut]


def video_store(settings: Settings) -> VideoStore:
    """The server's video directory, from its settings."""
    return VideoStore(
        settings.resolved_video_dir,
        max_bytes=min(settings.max_video_bytes, settings.max_internal_body_bytes),
        max_per_attempt=settings.max_videos_per_attempt,
        max_trajectory_bytes=min(settings.max_trajectory_bytes, settings.max_internal_body_bytes),
    )


def videos_of(*, submission: Submission, store: VideoStore) -> list[VideoOut]:
    """The videos stored for the submission's current attempt that its result lists; none in a
    phase whose seeds are secret (its episodes are hidden scenes, the same for everyone)."""
    if not submission.result or not submission.phase.public_seeds:
        return []
    try:
        result = EvaluationResult.model_validate(submission.result)
    except ValidationError:  # a document of an older format: shown without videos
        return []
    episodes: dict[tuple[str, str, int], EpisodeResult] = {
        (condition.name, task.env_id, e.index): e
        for condition in result.conditions
        for task in condition.tasks
        for e in task.episodes
    }
    show_seed = submission.phase.public_seeds
    out = []
    for video in result.videos:
        episode = episodes.get((video.condition, video.env_id, video.episode))
        try:
            name = video_name(condition=video.condition, env_id=video.env_id, episode=video.episode)
        except ValueError:
            continue
        stored = store.path(submission_id=submission.id, attempt=submission.attempt, name=name)
        if episode is None or stored is None:
            continue
        out.append(
            VideoOut(
                condition=video.condition,
                env_id=video.env_id,
                episode=video.episode,
                seed=episode.seed if show_seed else None,
                success_once=episode.success_once,
                success_at_end=episode.success_at_end,
                steps=episode.steps,
                failure=episode.failure_reason,
                url=f"/api/v1/submissions/{submission.id}/videos/{name}",
                poster=f"/api/v1/submissions/{submission.id}/videos/{name}/poster"
                if posters.has_poster(stored)
                else None,
            )
        )
    return out


@router.get("/submissions/{submission_id}/videos", tags=["submissions"])
def submission_videos(submission_id: Id, who: CallerDep, request: Request, db: DBDep) -> VideosOut:
    """The recorded episodes of the current attempt (whoever may see the submission)."""
    s = get_visible(db, submission_id=submission_id, user=who.user)
    store = video_store(services(request).settings)
    return VideosOut(
        submission_id=s.id, attempt=s.attempt, videos=videos_of(submission=s, store=store)
    )


def listed_video(
    db: Session, *, submission_id: int, name: str, user: User | None, store: VideoStore
) -> FilePath:
    """The stored file of one listed video of the current attempt, to whoever may see the
    submission; NotFound otherwise (for anyone else, as if the submission did not exist)."""
    s = get_visible(db, submission_id=submission_id, user=user)
    listed = {v.url.rsplit("/", 1)[-1] for v in videos_of(submission=s, store=store)}
    path = store.path(submission_id=s.id, attempt=s.attempt, name=name)
    if name not in listed or path is None:
        raise NotFound(f"no video {name!r}")
    return path


@router.get(
    "/submissions/{submission_id}/videos/{name}",
    tags=["submissions"],
    response_class=FileResponse,
    responses={200: {"content": {MEDIA_TYPE: {}}, "description": "the episode's MP4"}},
)
def submission_video(
    submission_id: Id, name: VideoName, who: CallerDep, request: Request, db: DBDep
) -> FileResponse:
    """One episode video of the current attempt, as MP4 (Range requests for seeking)."""
    store = video_store(services(request).settings)
    path = listed_video(db, submission_id=submission_id, name=name, user=who.user, store=store)
    return FileResponse(path, media_type=MEDIA_TYPE, headers={"Cache-Control": "private"})


@router.get(
    "/submissions/{submission_id}/videos/{name}/poster",
    tags=["submissions"],
    response_class=FileResponse,
    responses={200: {"content": {posters.MEDIA_TYPE: {}}, "description": "its first frame"}},
)
def submission_video_poster(
    submission_id: Id, name: VideoName, who: CallerDep, request: Request, db: DBDep
) -> FileResponse:
    """The first frame of one episode video, as JPEG (made on first request, then kept)."""
    store = video_store(services(request).settings)
    path = listed_video(db, submission_id=submission_id, name=name, user=who.user, store=store)
    poster = posters.poster(video=path, max_bytes=store.max_bytes)
    if poster is None:
        raise NotFound(f"no poster can be made of video {name!r}")
    return FileResponse(poster, media_type=posters.MEDIA_TYPE, headers={"Cache-Control": "private"})
