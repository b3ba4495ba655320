"""The internal API workers call, ``/internal/v1`` (not in the public OpenAPI document).

Authenticated by the worker token (``MANIEVAL_WORKER_TOKEN``, and during a rotation also
``MANIEVAL_WORKER_TOKEN_NEXT``), which lives only in the workers' environment: policy
containers never receive it, and have no network to use it on anyway. A worker holds no
database URL and no server secret: it claims work, is handed the evaluation with its concrete
seeds, and reports through here. Every report names its (submission, attempt) and is
idempotent (`reports.py`).
"""

from __future__ import annotations

import hmac
from collections.abc import Callable
from typing import Annotated

from fastapi import APIRouter, Depends, Path, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from internal_api.schemas import (
    Assignment,
    ClaimIn,
    FinalReport,
    ProgressReport,
    ReconcileOut,
    ReportOut,
    RestartOut,
    RunningReport,
    Silent,
    State,
)
from server.kit.deps import DBDep
from server.kit.errors import Unauthorized
from server.submissions.deps import services
from server.submissions.reconcile import Timeouts, reconcile, silent, timeouts_of
from server.submissions.reports import (
    check_running,
    current_state,
    report_final,
    report_progress,
    report_running,
)
from server.submissions.trajectories import merge_written
from server.submissions.video_store import (
    MEDIA_TYPE,
    POSTER_MEDIA_TYPE,
    TRAJECTORY_MEDIA_TYPES,
    NotATrajectory,
    NotAVideo,
    VideoStore,
)
from server.submissions.videos import video_store
from server.submissions.work import assignment, claim_next, end_restarted

Id = Annotated[int, Path(ge=1, le=2**31 - 1)]
VideoName = Annotated[str, Path(min_length=1, max_length=300)]
WorkerName = Annotated[str, Path(min_length=1, max_length=200, pattern=r"^[\x21-\x7e]+$")]


def require_worker(request: Request) -> None:
    """The worker token, compared in constant time; user tokens and sessions do not open it."""
    settings = services(request).settings
    scheme, _, value = request.headers.get("authorization", "").partition(" ")
    sent = value.encode("utf-8", "surrogateescape")
    accepted = [settings.secret("worker_token")]
    if settings.worker_token_next is not None:
        accepted.append(settings.worker_token_next.get_secret_value())
    matches = [hmac.compare_digest(sent, token.encode()) for token in accepted]
    if scheme.lower() != "bearer" or not any(matches):
        raise Unauthorized("worker token required")


router = APIRouter(
    prefix="/internal/v1", include_in_schema=False, dependencies=[Depends(require_worker)]
)
ATTEMPT = "/submissions/{submission_id}/attempts/{attempt}"


def _out(db: DBDep, submission_id: int, applied: bool) -> ReportOut:
    return ReportOut(applied=applied, state=current_state(db, submission_id=submission_id))


@router.post("/claims", response_model=Assignment, responses={204: {"description": "no work"}})
def claim(body: ClaimIn, request: Request, db: DBDep) -> Response:
    """Claim the fairest queued submission: 200 with its evaluation, or 204."""
    settings = services(request).settings
    seed_secret = settings.secret("seed_secret").encode()
    while True:
        claimed = claim_next(
            db, worker=body.worker, max_running_per_user=settings.max_running_per_user, commit=False
        )
        if claimed is None:
            return Response(status_code=204)
        sid, attempt = claimed
        try:
            handed = assignment(db, submission_id=sid, attempt=attempt, seed_secret=seed_secret)
        except ValueError as exc:  # a suite this version cannot plan: ours, with the reason
            report_final(db, sid, attempt, State.ERROR, f"cannot run: {exc}")
            db.commit()
            continue
        # The claim is committed with its evaluation in hand: if the database fails before
        # this, the worker's retry finds the submission still queued (not orphaned `launching`).
        db.commit()
        return JSONResponse(handed.model_dump(mode="json"))


@router.get(ATTEMPT)
def get_assignment(submission_id: Id, attempt: Id, request: Request, db: DBDep) -> Assignment:
    """A running attempt's evaluation again, for a new watcher of its Kubernetes Job."""
    secret = services(request).settings.secret("seed_secret").encode()
    return assignment(db, submission_id=submission_id, attempt=attempt, seed_secret=secret)


@router.post(f"{ATTEMPT}/running")
def post_running(submission_id: Id, attempt: Id, body: RunningReport, db: DBDep) -> ReportOut:
    applied = report_running(
        db, submission_id, attempt, reason=body.reason, deadline_s=body.deadline_s
    )
    db.commit()
    return _out(db, submission_id, applied)


@router.post(f"{ATTEMPT}/progress")
def post_progress(submission_id: Id, attempt: Id, body: ProgressReport, db: DBDep) -> ReportOut:
    applied = report_progress(db, submission_id, attempt, body.progress)
    db.commit()
    return _out(db, submission_id, applied)


@router.post(f"{ATTEMPT}/final")
def post_final(
    submission_id: Id, attempt: Id, body: FinalReport, request: Request, db: DBDep
) -> ReportOut:
    if body.result is not None:  # before the result is committed: a resent report merges again
        merge_written(
            video_store(services(request).settings),
            submission_id=submission_id,
            attempt=attempt,
            result=body.result,
        )
    applied = report_final(
        db,
        submission_id,
        attempt,
        body.state,
        body.reason,
        result=body.result,
        log_tail=body.log_tail,
        cause=body.cause,
    )
    db.commit()
    if body.cause is not None:  # it may run again: send it after the commit
        services(request).dispatcher.dispatch()
    return _out(db, submission_id, applied)


@router.put(f"{ATTEMPT}/videos/{{name}}", status_code=204)
async def put_video(submission_id: Id, attempt: Id, name: VideoName, request: Request) -> Response:
    """Store an episode video of a running attempt (MP4, named as the evaluator names it, at
    most `max_video_bytes`); 409 once the attempt has ended or been replaced."""
    if _media(request) != MEDIA_TYPE:
        raise NotAVideo(f"send the video as {MEDIA_TYPE}")
    await _keep(request, submission_id, attempt, name, VideoStore.store)
    return Response(status_code=204)


@router.put(f"{ATTEMPT}/videos/{{name}}/poster", status_code=204)
async def put_poster(submission_id: Id, attempt: Id, name: VideoName, request: Request) -> Response:
    """Store the poster (its first frame, JPEG) of a stored video of a running attempt; 409
    once the attempt has ended or been replaced."""
    if _media(request) != POSTER_MEDIA_TYPE:
        raise NotAVideo(f"send the poster as {POSTER_MEDIA_TYPE}")
    await _keep(request, submission_id, attempt, name, VideoStore.store_poster)
    return Response(status_code=204)


@router.put(f"{ATTEMPT}/trajectories/{{name}}", status_code=204)
async def put_trajectory(
    submission_id: Id, attempt: Id, name: VideoName, request: Request
) -> Response:
    """Store a task run's trajectory file of a running attempt (`.h5` as HDF5, `.json` as
    JSON, named as the evaluator names them); 409 once the attempt has ended or been
    replaced."""
    if _media(request) != TRAJECTORY_MEDIA_TYPES.get(name[name.rfind(".") :]):
        raise NotATrajectory("send a trajectory's .h5 as application/x-hdf5, its .json as JSON")
    await _keep(request, submission_id, attempt, name, VideoStore.store_trajectory)
    return Response(status_code=204)


def _media(request: Request) -> str:
    return request.headers.get("content-type", "").partition(";")[0].strip()


async def _keep(
    request: Request, submission_id: int, attempt: int, name: str, keep: Callable[..., None]
) -> None:
    """Keep an uploaded file of a running attempt with `keep` (a `VideoStore` method, which
    checks the name and the content)."""
    data = await request.body()  # bounded by max_internal_body_bytes before it is read

    def kept() -> None:
        svc = services(request)
        with svc.sessions() as db:
            check_running(db, submission_id=submission_id, attempt=attempt)
        store = video_store(svc.settings)
        keep(store, submission_id=submission_id, attempt=attempt, name=name, data=data)

    await run_in_threadpool(kept)


def _timeouts(request: Request) -> Timeouts:
    return timeouts_of(services(request).settings)


@router.get("/attempts/silent")
def get_silent(db: DBDep, request: Request) -> Silent:
    return Silent(attempts=silent(db, timeouts=_timeouts(request)))


@router.post("/reconcile")
def post_reconcile(request: Request) -> ReconcileOut:
    svc = services(request)
    return reconcile(svc.sessions, svc.dispatcher.work, timeouts=_timeouts(request))


@router.post("/workers/{worker}/restarted")
def post_restarted(worker: WorkerName, db: DBDep) -> RestartOut:
    ended = end_restarted(db, worker=worker)
    db.commit()
    return RestartOut(ended=ended)
