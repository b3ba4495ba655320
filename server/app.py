"""The FastAPI application: ``create_app(settings)`` wires the API, the web pages, the queue
and the worker."""

from __future__ import annotations

import hmac
import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Protocol

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from sqlalchemy import select, text
from sqlalchemy.orm import Session, sessionmaker
from starlette.exceptions import HTTPException as StarletteHTTPException

from server import api, internal, web, web_support
from server.db import make_engine, session_factory
from server.deps import Services
from server.dispatch import Dispatcher, InlineQueue, WorkQueue
from server.errors import AppError, ErrorBody, ErrorDetail, Invalid, Unauthorized, Unavailable
from server.image_refs import (
    ImageError,
    ImageReference,
    RegistryUnavailable,
    ResolvedImage,
    parse_reference,
)
from server.images import RegistryClient
from server.models import State, Submission
from server.observability import HttpMetrics, ServiceCollector
from server.ratelimit import MemoryRateLimiter, RateLimiter
from server.settings import Settings
from server.submissions import LOCAL_PREFIX, Resolved, Resolver, transition

log = logging.getLogger(__name__)
SWEEP_INTERVAL_S = 5.0
RECONCILE_EVERY = 6  # sweeps: every 30 s


class Registry(Protocol):
    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage: ...


def image_resolver(settings: Settings, registry: Registry | None = None) -> Resolver:
    """Validate a submitted reference and pin it through the registry; every problem is a 422
    on the `image` field."""
    client = registry or RegistryClient(
        allowed_registries=settings.allowed_registries,
        insecure_registries=settings.insecure_registries,
        timeout=settings.registry_timeout,
    )

    def resolve(image: str) -> Resolved:
        if image.startswith(LOCAL_PREFIX):
            return _resolve_local(image, settings)
        try:
            resolved = client.resolve(parse_reference(image), max_bytes=settings.max_image_bytes)
        except RegistryUnavailable as exc:  # ours or theirs, not the participant's: retry later
            raise Unavailable(str(exc), fields={"image": str(exc)}) from None
        except ImageError as exc:
            raise Invalid(str(exc), fields={"image": str(exc)}) from None
        return Resolved(pinned=resolved.pinned, size_bytes=resolved.size_bytes)

    return resolve


def _resolve_local(image: str, settings: Settings) -> Resolved:
    from worker.run import local_policies

    if not settings.allow_local_policies:
        raise Invalid(
            "this server does not accept local policies",
            fields={"image": "submit a container image reference"},
        )
    name = image.removeprefix(LOCAL_PREFIX)
    known = local_policies()
    if name not in known:
        raise Invalid(
            f"no bundled policy {name!r}", fields={"image": f"one of: {', '.join(sorted(known))}"}
        )
    return Resolved(pinned=image, size_bytes=None)


def inline_queue(sessions: sessionmaker[Session], settings: Settings) -> InlineQueue:
    from worker.run import run_next

    def drain(_sid: int, _attempt: int) -> None:
        # A message is a wake-up: run the fairest queued submissions until none can be claimed.
        while run_next(sessions, settings) is not None:
            pass

    return InlineQueue(drain, threads=settings.inline_workers)


def recover_inline(sessions: sessionmaker[Session], work: WorkQueue) -> None:
    """After a restart of the embedded server: runs it had in flight died with it (ended
    `error`, which burns no quota, so the owner may resubmit); queued ones are sent again."""
    with sessions.begin() as db:
        for s in db.scalars(
            select(Submission).where(Submission.state.in_([State.LAUNCHING, State.RUNNING]))
        ):
            transition(
                db,
                s.id,
                s.attempt,
                State.ERROR,
                "the server stopped during the evaluation; submit again or ask for a re-run",
            )
        pending = db.execute(
            select(Submission.id, Submission.attempt)
            .where(Submission.state == State.QUEUED)
            .order_by(Submission.id)
        ).all()
    for sid, attempt in pending:
        work.enqueue(sid, attempt)


def create_app(
    settings: Settings,
    *,
    sessions: sessionmaker[Session] | None = None,
    work: WorkQueue | None = None,
    resolve: Resolver | None = None,
    limiter: RateLimiter | None = None,
    background: bool = True,
) -> FastAPI:
    """The app. Tests pass their own session factory, queue, resolver or limiter, and
    `background=False` to run without the outbox sweeper and the embedded worker thread."""
    if sessions is None:
        sessions = session_factory(make_engine(settings.resolved_database_url))
    inline: InlineQueue | None = None
    if work is None:
        if settings.queue == "celery":
            from worker.queue import CeleryQueue

            work = CeleryQueue(settings)
        else:
            inline = inline_queue(sessions, settings)
            work = inline
    if limiter is None:
        limiter = _limiter(settings)
    dispatcher = Dispatcher(sessions, work)
    svc = Services(
        settings=settings,
        sessions=sessions,
        limiter=limiter,
        resolve=resolve or image_resolver(settings),
        dispatcher=dispatcher,
    )
    stop = threading.Event()

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        sweeper = threading.Thread(
            target=_sweep,
            args=(dispatcher, stop, sessions, inline, settings),
            name="manieval-sweep",
            daemon=True,
        )
        if inline is not None and background:
            recover_inline(sessions, inline)
            inline.start()
        if background:
            sweeper.start()
        try:
            yield
        finally:
            stop.set()
            if inline is not None:
                inline.stop(timeout=5)

    app = FastAPI(
        title="ManiEval",
        version="1.0",
        summary="Evaluation service for simulated robot-manipulation policies",
        lifespan=lifespan,
    )
    app.state.services = svc
    app.state.inline_queue = inline
    app.include_router(api.router)
    app.include_router(internal.router)
    web.install(app)
    _install_error_handlers(app)

    _install_monitoring(app, sessions, settings)
    return app


def _install_monitoring(app: FastAPI, sessions: sessionmaker[Session], settings: Settings) -> None:
    """Liveness, readiness and Prometheus metrics (docs/server.md, Monitoring)."""
    registry = CollectorRegistry()
    registry.register(ServiceCollector(sessions))
    app.middleware("http")(HttpMetrics(registry))

    @app.get("/healthz", include_in_schema=False)
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", include_in_schema=False)
    def readyz() -> JSONResponse:
        try:
            with sessions() as db:
                db.execute(text("SELECT 1"))
        except Exception:  # the detail may name hosts and users: the log has it, not the answer
            log.exception("readiness: the database does not answer")
            return JSONResponse({"status": "unavailable", "database": "unreachable"}, 503)
        if (problem := _broker_problem(settings)) is not None:
            log.warning("readiness: the broker does not answer: %s", problem)
            return JSONResponse({"status": "unavailable", "broker": "unreachable"}, 503)
        return JSONResponse({"status": "ok"})

    @app.get("/metrics", include_in_schema=False)
    def metrics(request: Request) -> Response:
        token = settings.metrics_token
        if token is not None:
            sent = request.headers.get("authorization", "").encode("utf-8", "surrogateescape")
            expected = f"Bearer {token.get_secret_value()}".encode()
            if not hmac.compare_digest(sent, expected):
                raise Unauthorized("send the metrics token: Authorization: Bearer <token>")
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


def _broker_problem(settings: Settings) -> str | None:
    """Why the Celery broker does not answer, or None (also when there is no broker)."""
    if settings.queue != "celery":
        return None
    import redis

    try:
        with redis.Redis.from_url(
            settings.broker_url, socket_connect_timeout=2, socket_timeout=2
        ) as broker:
            broker.ping()
    except Exception as exc:
        return str(exc) or type(exc).__name__
    return None


def _limiter(settings: Settings) -> RateLimiter:
    if settings.rate_limit_backend == "redis":
        import redis

        from server.ratelimit import RedisRateLimiter

        return RedisRateLimiter(redis.Redis.from_url(settings.redis_url))
    return MemoryRateLimiter()


def _sweep(
    dispatcher: Dispatcher,
    stop: threading.Event,
    sessions: sessionmaker[Session],
    inline: InlineQueue | None,
    settings: Settings,
) -> None:
    """Send what the outbox still holds; in the embedded mode also reconcile (with Celery,
    beat does that)."""
    from worker.reconcile import reconcile
    from worker.run import runtime_cleaners

    cleaners = runtime_cleaners(settings)
    passes = 0
    while not stop.wait(SWEEP_INTERVAL_S):
        dispatcher.dispatch()
        passes += 1
        if inline is not None and passes % RECONCILE_EVERY == 0:
            try:
                reconcile(sessions, inline, cleaners=cleaners)
            except Exception:
                log.exception("reconciling failed; the next pass will try again")


def _install_error_handlers(app: FastAPI) -> None:
    """One error body for the API (JSON), and its HTML twin for the web pages."""

    def respond(
        request: Request, status: int, detail: ErrorDetail, headers: dict[str, str] | None = None
    ) -> Response:
        if web_support.wants_html(request):
            page = web_support.error_page(request, status, _TITLES.get(status, "Error"), detail)
            page.headers.update(headers or {})
            return page
        body = ErrorBody(error=detail).model_dump(mode="json", exclude_none=True)
        return JSONResponse(body, status_code=status, headers=headers)

    @app.exception_handler(AppError)
    async def app_error(request: Request, exc: AppError) -> Response:
        detail = ErrorDetail.model_validate(exc.body()["error"])
        return respond(request, exc.status, detail, exc.headers())

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> Response:
        fields: dict[str, str] = {}
        for error in exc.errors():
            loc = [str(part) for part in error.get("loc", ()) if part not in ("body", "query")]
            fields[".".join(loc) or "request"] = str(error.get("msg", "invalid"))
        detail = ErrorDetail(code="invalid", message="the request is not valid", fields=fields)
        return respond(request, 422, detail)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        detail = ErrorDetail(code=code, message=str(exc.detail))
        return respond(request, exc.status_code, detail, getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def crash(request: Request, exc: Exception) -> Response:
        log.exception("unhandled error", exc_info=exc)
        detail = ErrorDetail(code="internal", message="internal error; it has been logged")
        return respond(request, 500, detail)


_TITLES = {
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
