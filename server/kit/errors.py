"""The errors the API reports, all in one body shape:

    {"error": {"code": "quota_exceeded", "message": "...", "fields": {"image": "..."}, ...}}

``code`` is stable for programs, ``message`` is for people, ``fields`` maps form fields to
their problems (shown next to the field by the web pages).
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel


class ErrorDetail(BaseModel):
    code: str
    message: str
    fields: dict[str, str] = {}
    retry_after: float | None = None
    resets_at: str | None = None


class ErrorBody(BaseModel):
    error: ErrorDetail


class AppError(Exception):
    status: ClassVar[int] = 400
    code: ClassVar[str] = "bad_request"

    def __init__(self, message: str, *, fields: dict[str, str] | None = None, **extra: Any) -> None:
        super().__init__(message)
        self.message = message
        self.fields = fields or {}
        self.extra = extra

    def body(self) -> dict[str, Any]:
        detail = ErrorDetail(code=self.code, message=self.message, fields=self.fields, **self.extra)
        return ErrorBody(error=detail).model_dump(mode="json", exclude_none=True)

    def headers(self) -> dict[str, str]:
        return {}


class Invalid(AppError):
    status = 422
    code = "invalid"


class Unauthorized(AppError):
    status = 401
    code = "unauthorized"

    def headers(self) -> dict[str, str]:
        return {"WWW-Authenticate": "Bearer"}


class Forbidden(AppError):
    status = 403
    code = "forbidden"


class NotFound(AppError):
    status = 404
    code = "not_found"


class Conflict(AppError):
    status = 409
    code = "conflict"


class RateLimited(AppError):
    status = 429
    code = "rate_limited"

    def __init__(self, message: str, *, retry_after: float) -> None:
        super().__init__(message, retry_after=round(retry_after, 3))
        self.retry_after = retry_after

    def headers(self) -> dict[str, str]:
        return {"Retry-After": str(max(1, int(self.retry_after + 0.999)))}


class QuotaExceeded(RateLimited):
    code = "quota_exceeded"

    def __init__(self, message: str, *, retry_after: float, resets_at: str | None) -> None:
        super().__init__(message, retry_after=retry_after)
        if resets_at is not None:
            self.extra["resets_at"] = resets_at


class Unavailable(AppError):
    status = 503
    code = "unavailable"

    def headers(self) -> dict[str, str]:
        retry_after = self.extra.get("retry_after")
        return {} if retry_after is None else {"Retry-After": str(max(1, int(retry_after)))}


ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorBody} for status in (400, 401, 403, 404, 409, 422, 429, 503)
}
