"""One error body for the API (JSON), and its HTML twin for the web pages."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Mapping
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from server.kit import pages
from server.kit.errors import AppError, ErrorBody, ErrorDetail
from server.kit.limits import RequestGuard

log = logging.getLogger(__name__)

TITLES = {
    401: "Please log in",
    403: "Not allowed",
    404: "Not found",
    405: "Not allowed",
    409: "Not possible now",
    422: "Something is not right",
    429: "Too many requests",
    500: "Something went wrong on our side",
    503: "Unavailable; try again soon",
}


_CHOICES = re.compile(r"^\^\(([\w.-]+(?:\|[\w.-]+)+)\)\$$")


def readable(error: Mapping[str, Any]) -> str:
    """A validation problem as people read it: a pattern of choices, `^(asc|desc)$`, says
    "must be one of: asc, desc" rather than quote the pattern."""
    if error.get("type") == "string_pattern_mismatch":
        pattern = str((error.get("ctx") or {}).get("pattern", ""))
        if (choices := _CHOICES.match(pattern)) is not None:
            return "must be one of: " + ", ".join(choices.group(1).split("|"))
        return f"is not in the expected form ({pattern})"
    return str(error.get("msg", "invalid"))


PageViewer = Callable[[Request], pages.Viewer | None]
"""Who is looking at an error page, read with a database session of its own (None: unknown)."""


def install_error_handlers(
    app: FastAPI, *, viewer: PageViewer | None, database_retry_after_s: int
) -> None:
    """Render every error, ours, FastAPI's and Starlette's, as the one error body; and put the
    request guard (server/kit/limits.py) in front of everything that reads a request. Error
    pages below 500 show the navigation of `viewer`, as every other page does; a request that
    meets the database unreachable is told to try again in `database_retry_after_s`."""
    app.add_middleware(RequestGuard)

    async def who(request: Request, status: int) -> pages.Viewer | None:
        if viewer is None or status >= 500 or not pages.wants_html(request):
            return None  # a 5xx may be the database's: the page then guesses from the cookie
        try:
            return await run_in_threadpool(viewer, request)
        except Exception:
            log.warning("an error page could not read its viewer", exc_info=True)
            return None

    async def respond(
        request: Request, status: int, detail: ErrorDetail, headers: dict[str, str] | None = None
    ) -> Response:
        if pages.wants_html(request):
            page = pages.error_page(
                request, status, TITLES.get(status, "Error"), detail, who=await who(request, status)
            )
            page.headers.update(headers or {})
            return page
        body = ErrorBody(error=detail).model_dump(mode="json", exclude_none=True)
        return JSONResponse(body, status_code=status, headers=headers)

    @app.exception_handler(AppError)
    async def app_error(request: Request, exc: AppError) -> Response:
        detail = ErrorDetail.model_validate(exc.body()["error"])
        return await respond(request, exc.status, detail, exc.headers())

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> Response:
        fields: dict[str, str] = {}
        for error in exc.errors():
            loc = [str(part) for part in error.get("loc", ()) if part not in ("body", "query")]
            fields[".".join(loc) or "request"] = readable(error)
        detail = ErrorDetail(code="invalid", message="the request is not valid", fields=fields)
        return await respond(request, 422, detail)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        detail = ErrorDetail(code=code, message=str(exc.detail))
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:
            headers["Allow"] = allowed_methods(request)
        return await respond(request, exc.status_code, detail, headers)

    @app.exception_handler(OperationalError)
    @app.exception_handler(InterfaceError)
    @app.exception_handler(PoolTimeout)
    async def database_unavailable(request: Request, exc: Exception) -> Response:
        # Not a bug and not the client's fault: the database is down or restarting. Clients
        # (the CLI, workers) retry after Retry-After; the log keeps one line, not a traceback.
        log.warning(
            "the database is unavailable: %s", str(exc).splitlines()[0] if str(exc) else exc
        )
        detail = ErrorDetail(
            code="unavailable", message="the database is unavailable; try again shortly"
        )
        return await respond(request, 503, detail, {"Retry-After": str(database_retry_after_s)})

    @app.exception_handler(Exception)
    async def crash(request: Request, exc: Exception) -> Response:
        log.exception("unhandled error", exc_info=exc)
        detail = ErrorDetail(code="internal", message="internal error; it has been logged")
        return await respond(request, 500, detail)


HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(request: Request) -> str:
    """Every method some route answers at this path (Starlette's 405 names only the first
    route's). Asked of the routes themselves, so included routers and pages count too."""
    allowed = []
    for method in HTTP_METHODS:
        scope = {**request.scope, "method": method}
        if any(route.matches(scope)[0] == Match.FULL for route in request.app.router.routes):
            allowed.append(method)
    return ", ".join(allowed)
