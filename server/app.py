"""The FastAPI application: ``create_app(settings)`` wires the routers of each domain, the web
pages, the error handlers, monitoring, the queue and the embedded worker."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from sqlalchemy.orm import Session, sessionmaker

from server.accounts import api as accounts_api
from server.accounts import pages as accounts_pages
from server.challenges import api as challenges_api
from server.challenges import pages as challenges_pages
from server.kit import pages
from server.kit.db import make_engine, session_factory
from server.kit.deps import Services
from server.kit.handlers import install_error_handlers
from server.kit.observability import install_monitoring
from server.kit.ratelimit import MemoryRateLimiter, RateLimiter
from server.kit.settings import Settings
from server.leaderboard import api as leaderboard_api
from server.leaderboard import pages as leaderboard_pages
from server.submissions import api as submissions_api
from server.submissions import events, internal, submit_pages
from server.submissions import pages as submissions_pages
from server.submissions.images import image_resolver
from server.submissions.outbox import Dispatcher, WorkQueue
from server.submissions.service import Resolver, end_interrupted
from worker.embedded import InlineQueue

log = logging.getLogger(__name__)
SWEEP_INTERVAL_S = 5.0
RECONCILE_EVERY = 6  # sweeps: every 30 s


def inline_queue(sessions: sessionmaker[Session], settings: Settings) -> InlineQueue:
    from worker.run import run_next

    def drain(_sid: int, _attempt: int) -> None:
        # A message is a wake-up: run the fairest queued submissions until none can be claimed.
        while run_next(sessions, settings) is not None:
            pass

    return InlineQueue(drain, threads=settings.inline_workers)


def recover_inline(sessions: sessionmaker[Session], work: WorkQueue) -> None:
    """After a restart of the embedded server: end the runs it had in flight, and send the
    queued ones again."""
    with sessions.begin() as db:
        pending = end_interrupted(db)
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
    app.state.score_history = challenges_pages.ScoreHistory()
    app.state.event_timing = events.StreamTiming()
    app.state.event_slots = events.StreamSlots()
    for api in (accounts_api, challenges_api, leaderboard_api, submissions_api, internal):
        app.include_router(api.router)
    pages.install(
        app,
        [
            challenges_pages.router,
            accounts_pages.router,
            leaderboard_pages.router,
            submit_pages.router,
            submissions_pages.router,
            events.router,
        ],
    )
    install_error_handlers(app)
    install_monitoring(app, sessions, settings)
    return app


def _limiter(settings: Settings) -> RateLimiter:
    if settings.rate_limit_backend == "redis":
        import redis

        from server.kit.ratelimit import RedisRateLimiter

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
