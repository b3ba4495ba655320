"""Episode trajectories of a submission's current attempt, in ManiSkill's format: one
`<condition>--<Task>.h5` + `.json` per task run (docs/trajectories.md).

Public-seed phases: whoever may see the submission. Secret-seed phases: organizers
(administrators) only, since a trajectory's reset seed and first env state reveal the hidden
scenes; anyone else who may see the submission gets 403, everyone else 404.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path as FilePath
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field, ValidationError
from sqlalchemy.orm import Session

from evaluator.results import EvaluationResult, TaskResult
from evaluator.trajectory import PARTS, merge_parts, trajectory_stem
from server.accounts.deps import CallerDep
from server.kit.deps import DBDep, Id
from server.kit.errors import ERROR_RESPONSES, Forbidden, NotFound
from server.models import Submission, User
from server.submissions.deps import services
from server.submissions.service import get_visible
from server.submissions.video_store import TRAJECTORIES, TRAJECTORY_MEDIA_TYPES, VideoStore
from server.submissions.videos import video_store

log = logging.getLogger(__name__)
router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)
TrajectoryName = Annotated[str, Path(min_length=1, max_length=300)]


class TrajectoryOut(BaseModel):
    """One task run's trajectories: its `.h5` and `.json`, replayable with ManiSkill's tool."""

    condition: str
    env_id: str
    episodes: int = Field(description="episodes of the task run that ran (each a traj_N)")
    h5_url: str = Field(description="the HDF5 file (actions, env states, success per step)")
    json_url: str = Field(description="its JSON (env kwargs, seeds, episodes)")
    bytes: int = Field(description="the two files' size together")


class TrajectoriesOut(BaseModel):
    submission_id: int
    attempt: int
    trajectories: list[TrajectoryOut]


def may_download_trajectories(submission: Submission, user: User | None) -> bool:
    """Whether `user`, who may see the submission, may download its trajectories."""
    return submission.phase.public_seeds or (user is not None and user.is_admin)


def trajectories_of(*, submission: Submission, store: VideoStore) -> list[TrajectoryOut]:
    """The task runs of the current attempt's result whose two files are stored."""
    result = _result_of(submission)
    if result is None:
        return []
    out = []
    for condition, task, stem in _task_runs(result):
        files = [
            store.trajectory_path(
                submission_id=submission.id, attempt=submission.attempt, name=stem + suffix
            )
            for suffix in TRAJECTORY_MEDIA_TYPES
        ]
        if None in files:
            continue
        base = f"/api/v1/submissions/{submission.id}/trajectories/{stem}"
        out.append(
            TrajectoryOut(
                condition=condition,
                env_id=task.env_id,
                episodes=sum(e.failure != "not_run" for e in task.episodes),
                h5_url=f"{base}.h5",
                json_url=f"{base}.json",
                bytes=sum(f.stat().st_size for f in files if f is not None),
            )
        )
    return out


def merge_written(
    store: VideoStore, *, submission_id: int, attempt: int, result: EvaluationResult
) -> None:
    """Merge the trajectory parts Kubernetes pods wrote into the attempt's directory (each
    shard's own, `evaluator.job`) into one file pair per task run, when the attempt's final
    report brings its result. Repeating it (a resent report) is harmless; a merge that fails
    costs the trajectories, never the result."""
    directory = store.attempt_dir(submission_id=submission_id, attempt=attempt) / TRAJECTORIES
    if not (directory / PARTS).is_dir():
        return  # uploaded by a worker, or not recorded
    try:
        merge_parts(directory, [stem for _c, _t, stem in _task_runs(result)])
    except (OSError, ValueError, KeyError) as exc:
        log.warning(
            "trajectories of submission %s attempt %s not merged: %s", submission_id, attempt, exc
        )


def _result_of(submission: Submission) -> EvaluationResult | None:
    if not submission.result:
        return None
    try:
        return EvaluationResult.model_validate(submission.result)
    except ValidationError:  # a document of an older format: no trajectories
        return None


def _task_runs(result: EvaluationResult) -> Iterator[tuple[str, TaskResult, str]]:
    """Each task run of `result` that has a trajectory name: condition, task and stem."""
    for condition in result.conditions:
        for task in condition.tasks:
            try:
                stem = trajectory_stem(condition=condition.name, env_id=task.env_id)
            except ValueError:
                continue
            yield condition.name, task, stem


def downloadable(db: Session, *, submission_id: int, user: User | None) -> Submission:
    """The submission, if `user` may download its trajectories: NotFound to whoever may not
    see it, Forbidden to anyone else but organizers in a secret-seed phase."""
    s = get_visible(db, submission_id=submission_id, user=user)
    if not may_download_trajectories(s, user):
        raise Forbidden(
            f"submission {submission_id} is in a phase whose seeds are secret: its "
            "trajectories, which reveal the seeds' scenes, are visible to organizers only"
        )
    return s


def listed_trajectories(
    db: Session, *, submission_id: int, user: User | None, store: VideoStore
) -> tuple[Submission, list[TrajectoryOut]]:
    """The submission and its stored trajectories; NotFound, saying so, when there are none."""
    s = downloadable(db, submission_id=submission_id, user=user)
    found = trajectories_of(submission=s, store=store)
    if not found:
        raise NotFound(
            f"submission {submission_id} has no recorded trajectories (attempt {s.attempt}: "
            "not finished, or evaluated where trajectories are not recorded)"
        )
    return s, found


@router.get("/submissions/{submission_id}/trajectories", tags=["submissions"])
def submission_trajectories(
    submission_id: Id, who: CallerDep, request: Request, db: DBDep
) -> TrajectoriesOut:
    """The current attempt's trajectories in ManiSkill's format, one pair of files per task
    run (public-seed phases: whoever may see the submission; secret-seed: organizers)."""
    store = video_store(services(request).settings)
    s, found = listed_trajectories(db, submission_id=submission_id, user=who.user, store=store)
    return TrajectoriesOut(submission_id=s.id, attempt=s.attempt, trajectories=found)


@router.get(
    "/submissions/{submission_id}/trajectories/{name}",
    tags=["submissions"],
    response_class=FileResponse,
    responses={
        200: {
            "content": {media: {} for media in TRAJECTORY_MEDIA_TYPES.values()},
            "description": "a task run's trajectory file (.h5 or .json)",
        }
    },
)
def submission_trajectory(
    submission_id: Id, name: TrajectoryName, who: CallerDep, request: Request, db: DBDep
) -> FileResponse:
    """One listed trajectory file of the current attempt, to download."""
    store = video_store(services(request).settings)
    path = _listed_file(db, submission_id=submission_id, name=name, user=who.user, store=store)
    return FileResponse(
        path,
        media_type=TRAJECTORY_MEDIA_TYPES[path.suffix],
        filename=name,
        headers={"Cache-Control": "private"},
    )


def _listed_file(
    db: Session, *, submission_id: int, name: str, user: User | None, store: VideoStore
) -> FilePath:
    s, found = listed_trajectories(db, submission_id=submission_id, user=user, store=store)
    listed = {url.rsplit("/", 1)[-1] for t in found for url in (t.h5_url, t.json_url)}
    path = store.trajectory_path(submission_id=s.id, attempt=s.attempt, name=name)
    if name not in listed or path is None:
        raise NotFound(f"no trajectory file {name!r}")
    return path
