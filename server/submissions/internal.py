"""The internal API workers report to, ``/internal/v1`` (not in the public OpenAPI document).

Authenticated by the worker token (``MANIEVAL_WORKER_TOKEN``), which lives only in the worker's
environment: policy containers never receive it, and have no network to use it on anyway.
Every report names its (submission, attempt) and is idempotent.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import APIRouter, Depends, Path, Request
from pydantic import ValidationError

from evaluator.results import EvaluationResult
from server.kit.deps import DBDep, services
from server.kit.errors import Invalid, Unauthorized
from server.submissions.reports import current_state, report_final, report_progress, report_state
from server.submissions.schemas import FinalReport, ProgressReport, ReportOut, StateReport

Id = Annotated[int, Path(ge=1, le=2**31 - 1)]


def require_worker(request: Request) -> None:
    expected = services(request).settings.secret("worker_token")
    scheme, _, value = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(value.encode(), expected.encode()):
        raise Unauthorized("worker token required")


router = APIRouter(
    prefix="/internal/v1/submissions/{submission_id}/attempts/{attempt}",
    include_in_schema=False,
    dependencies=[Depends(require_worker)],
)


def _out(db: DBDep, submission_id: Id, applied: bool) -> ReportOut:
    return ReportOut(applied=applied, state=current_state(db, submission_id=submission_id))


@router.post("/state")
def post_state(submission_id: Id, attempt: Id, body: StateReport, db: DBDep) -> ReportOut:
    applied = report_state(db, submission_id, attempt, body.state, body.reason)
    db.commit()
    return _out(db, submission_id, applied)


@router.post("/progress")
def post_progress(submission_id: Id, attempt: Id, body: ProgressReport, db: DBDep) -> ReportOut:
    applied = report_progress(db, submission_id, attempt, dict(body.progress))
    db.commit()
    return _out(db, submission_id, applied)


@router.post("/final")
def post_final(
    submission_id: Id, attempt: Id, body: Annotated[FinalReport, ...], db: DBDep
) -> ReportOut:
    result = None
    if body.result is not None:
        try:
            result = EvaluationResult.model_validate(body.result)
        except ValidationError as exc:
            raise Invalid(f"the result document does not validate: {exc}") from None
    applied = report_final(
        db,
        submission_id,
        attempt,
        body.state,
        body.reason,
        result=result,
        log_tail=body.log_tail,
    )
    db.commit()
    return _out(db, submission_id, applied)
