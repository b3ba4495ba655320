"""The request guard: the first thing a request meets, before any parsing, CSRF or
authentication work.

- A request body larger than the setting (`max_body_bytes`, `max_internal_body_bytes` for the
  workers' `/internal/` reports) is refused with 413 as soon as its declared `Content-Length`
  or its streamed length passes the limit. The body is read into memory up to the limit and
  handed on only when complete, so nothing behind the guard ever sees a larger one.
- A path or query string holding a character that Postgres or the pages cannot hold (NUL,
  another control character, a lone surrogate, U+FFFE, U+FFFF; `server/kit/schemas.py`) is
  refused with 422.

A pure ASGI middleware (not Starlette's `BaseHTTPMiddleware`), so it adds no task and no copy.
"""

from __future__ import annotations

from urllib.parse import parse_qsl

from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.kit import pages
from server.kit.errors import ErrorBody, ErrorDetail
from server.kit.schemas import text_problem

INTERNAL_PREFIX = "/internal/"


class BodyTooLarge(Exception):
    """The request body passed the limit (raised to stop reading, never leaves the guard)."""


class _Disconnected(Exception):
    """The client went away before its body was complete."""


class RequestGuard:
    """Refuse oversized bodies (413) and unstorable characters in the URL (422)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if (problem := _url_problem(scope)) is not None:
            await _refuse(scope, send, 422, "invalid", problem[1], {problem[0]: problem[1]})
            return
        limit = _limit(scope)
        declared = _content_length(scope)
        if declared is not None and declared > limit:
            await _refuse_size(scope, send, limit)
            return
        if declared == 0 or not _may_have_body(scope, declared):
            await self.app(scope, receive, send)
            return
        try:
            body = await _read_body(receive, limit)
        except BodyTooLarge:
            await _refuse_size(scope, send, limit)
            return
        except _Disconnected:
            return  # nobody is left to answer
        await self.app(scope, _replay(body, receive), send)


def _limit(scope: Scope) -> int:
    settings = scope["app"].state.services.settings
    if str(scope["path"]).startswith(INTERNAL_PREFIX):
        return int(settings.max_internal_body_bytes)
    return int(settings.max_body_bytes)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope["headers"]:
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None  # the server (uvicorn, h11) refuses a malformed length itself
    return None


def _may_have_body(scope: Scope, declared: int | None) -> bool:
    if declared is not None:
        return True
    return any(name == b"transfer-encoding" for name, _ in scope["headers"])


async def _read_body(receive: Receive, limit: int) -> bytes:
    """The whole body, or BodyTooLarge as soon as more than `limit` bytes have arrived."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":  # the client went away
            raise _Disconnected
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            raise BodyTooLarge
        chunks.append(chunk)
        if not message.get("more_body", False):
            return b"".join(chunks)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A `receive` giving the read body once, then what the server says (a disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


def _url_problem(scope: Scope) -> tuple[str, str] | None:
    """(where, what is wrong) for the first unstorable character of the path or query."""
    if (problem := text_problem(str(scope["path"]))) is not None:
        return "path", f"the path {problem}"
    query = bytes(scope.get("query_string", b"")).decode("latin-1")
    for name, value in parse_qsl(query, keep_blank_values=True):
        if (problem := text_problem(name)) is not None:
            return "query", f"a query parameter's name {problem}"
        if (problem := text_problem(value)) is not None:
            return name, problem
    return None


async def _refuse_size(scope: Scope, send: Send, limit: int) -> None:
    message = f"the request body is larger than {limit} bytes"
    await _refuse(scope, send, 413, "too_large", message, {}, close=True)


async def _refuse(
    scope: Scope,
    send: Send,
    status: int,
    code: str,
    message: str,
    fields: dict[str, str],
    *,
    close: bool = False,
) -> None:
    detail = ErrorDetail(code=code, message=message, fields=fields)
    response = _response(scope, status, detail)
    if close:  # the unread rest of the body must not be taken for the next request
        response.headers["Connection"] = "close"

    async def no_body() -> Message:
        return {"type": "http.disconnect"}

    await response(scope, no_body, send)


def _response(scope: Scope, status: int, detail: ErrorDetail) -> Response:
    request = Request(scope)
    if pages.wants_html(request):
        title = "Too large" if status == 413 else "Something is not right"
        return pages.error_page(request, status, title, detail)
    body = ErrorBody(error=detail).model_dump(mode="json", exclude_none=True)
    return JSONResponse(body, status_code=status)
