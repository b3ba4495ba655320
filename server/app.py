"""The FastAPI application: ``create_app(settings)`` wires the routers of each domain, the web
pages, the error handlers, monitoring and the queue.

The server never imports the worker. With ``MANIEVAL_QUEUE=celery`` it sends wake-ups to the
broker by task name; on the embedded default the `manieval` CLI composes it with the embedded
worker (`manieval/service.py`) and hands that worker's queue in as `work`.
"""

from __future__ import annotations

import gc
import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from sqlalchemy.orm import Session, sessionmaker

from server.accounts import api as accounts_api
from server.accounts import pages as accounts_pages
from server.accounts.deps import error_page_viewer
from server.challenges import api as challenges_api
from server.challenges import pages as challenges_pages
from server.console import api as console_api
from server.console import pages as console_pages
from server.console import user_pages as console_user_pages
from server.downloads import api as downloads_api
from server.kit import pages
from server.kit.apidocs import mount_api_docs
from server.kit.db import make_engine, session_factory
from server.kit.handlers import install_error_handlers
from server.kit.observability import install_monitoring
from server.kit.ratelimit import MemoryRateLimiter, RateLimiter
from server.kit.settings import Settings
from server.leaderboard import api as leaderboard_api
from server.leaderboard import challenge_page, help_page
from server.leaderboard import pages as leaderboard_pages
from server.registry import api as registry_api
from server.services import Services
from server.submissions import admin_api as submissions_admin
from server.submissions import api as submissions_api
from server.submissions import events, internal, start_page, submit_pages
from server.submissions import pages as submissions_pages
from server.submissions import trajectories as submissions_trajectories
from server.submissions import videos as submissions_videos
from server.submissions.changes import ChangeFeed
from server.submissions.images import image_resolver
from server.submissions.outbox import CeleryQueue, Dispatcher, Unattached, WorkQueue
from server.submissions.service import Resolver
from server.teams import api as teams_api
from server.teams import pages as teams_pages

log = logging.getLogger(__name__)
SWEEP_INTERVAL_S = 5.0


_frozen = False


def _freeze_startup_objects() -> None:
    """Once per process, when the first app starts: exempt what exists (the app, its routes,
    templates, schemas; about 170,000 objects) from the cyclic garbage collector. They live as
    long as the process, and each full collection walked them all, pausing every request for
    110-150 ms every second or two under load (bench/leaderboard_load.py)."""
    global _frozen
    if not _frozen:
        gc.collect()
        gc.freeze()
        _frozen = True


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
    `background=False` to run without the outbox sweeper."""
    if sessions is None:
        sessions = session_factory(make_engine(settings.resolved_database_url))
    if work is None:
        if settings.queue == "celery":
            work = CeleryQueue(settings.broker_url, settings.celery_queue)
        else:
            work = Unattached()
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
    feed = ChangeFeed()

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        _freeze_startup_objects()
        sweeper = threading.Thread(
            target=_sweep, args=(dispatcher, stop), name="manieval-sweep", daemon=True
        )
        if background:
            sweeper.start()
        feed.listen(settings.resolved_database_url)  # other processes' changes, on Postgres
        try:
            yield
        finally:
            feed.close()
            stop.set()

    app = FastAPI(
        title="ManiEval",
        version="1.0",
        summary="Evaluation service for simulated robot-manipulation policies",
        lifespan=lifespan,
        docs_url=None,  # served from this server's own assets (`mount_api_docs`): works offline
        redoc_url=None,
    )
    app.state.services = svc
    app.state.score_history = challenge_page.ScoreHistory()
    app.state.event_timing = events.StreamTiming()
    app.state.event_slots = events.StreamSlots()
    app.state.change_feed = feed
    for api in (
        accounts_api,
        challenges_api,
        leaderboard_api,
        submissions_api,
        submissions_admin,
        submissions_videos,
        submissions_trajectories,
        internal,
    ):
        app.include_router(api.router)
    app.include_router(registry_api.router)
    app.include_router(registry_api.public)
    app.include_router(teams_api.router)
    app.include_router(downloads_api.router)
    app.include_router(console_api.router)
    pages.install(
        app,
        [
            challenges_pages.router,
            challenge_page.router,
            accounts_pages.router,
            leaderboard_pages.router,
            help_page.router,
            submit_pages.router,
            start_page.router,
            submissions_pages.router,
            events.router,
            teams_pages.router,
            console_pages.router,
            console_user_pages.router,
        ],
    )
    install_error_handlers(
        app, viewer=error_page_viewer, database_retry_after_s=settings.database_retry_after_s
    )
    mount_api_docs(app)
    install_monitoring(app, sessions, settings)
    return app


def _limiter(settings: Settings) -> RateLimiter:
    if settings.rate_limit_backend == "redis":
        import redis

        from server.kit.ratelimit import RedisRateLimiter

        return RedisRateLimiter(redis.Redis.from_url(settings.redis_url))
    return MemoryRateLimiter()


def _sweep(dispatcher: Dispatcher, stop: threading.Event) -> None:
    """Send what the outbox still holds (a broker outage, a crash between commit and send)."""
    while not stop.wait(SWEEP_INTERVAL_S):
        dispatcher.dispatch()
