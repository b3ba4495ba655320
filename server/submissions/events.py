"""Server-sent events: a submission's state changes and progress, as they happen.

`GET /submissions/{id}/events[?after=T]` streams every transition after transition id `T`
(or the `Last-Event-ID` a reconnecting browser sends), in order, so none is missed however the
reads fall; `progress` events while it runs; and `end` once it reaches a final state, after
which the stream closes. A stream reads the database when its submission changes
(`server/submissions/changes.py`: pushed on commit, through Postgres LISTEN/NOTIFY across
processes), not on a timer: an idle stream only sends its keep-alives, and reads again after
`fallback_s` without a signal (which, at the default, is also the stream's life). A comment line
keeps idle connections open through proxies, and a stream lasts at most `max_s` seconds: the
browser then reconnects where it left off. Each read uses its own short database session, so an
open stream holds no connection.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import sessionmaker
from starlette.concurrency import run_in_threadpool

from server.accounts import service as accounts
from server.kit.deps import SESSION_COOKIE, Id
from server.kit.errors import Unavailable
from server.models import State, User
from server.submissions.changes import ChangeFeed
from server.submissions.deps import services
from server.submissions.service import find_visible, get_visible, transitions_of

router = APIRouter(include_in_schema=False)


@dataclass(frozen=True)
class StreamTiming:
    fallback_s: float = 120.0  # read anyway after this long without a change signal
    keepalive_s: float = 15.0
    max_s: float = 120.0  # also bounds how long a server shutdown waits for open streams
    retry_ms: int = 3000  # how long the browser waits before reconnecting


class StreamSlots:
    """Bounds open streams, in all and per client address: each one polls the database, so
    without a bound a few hundred idle tabs (or a script) would take the thread pool."""

    def __init__(self, *, total: int = 200, per_client: int = 8) -> None:
        self.total, self.per_client = total, per_client
        self._open: dict[str, int] = {}
        self._lock = threading.Lock()

    def take(self, client: str) -> bool:
        with self._lock:
            if (
                sum(self._open.values()) >= self.total
                or self._open.get(client, 0) >= self.per_client
            ):
                return False
            self._open[client] = self._open.get(client, 0) + 1
            return True

    def give_back(self, client: str) -> None:
        with self._lock:
            left = self._open.get(client, 0) - 1
            if left > 0:
                self._open[client] = left
            else:
                self._open.pop(client, None)


@dataclass(frozen=True)
class PolledSubmission:
    """What one poll of a watched submission found: where it stands, and its new transitions."""

    state: State
    reason: str
    score: float | None
    progress: dict[str, Any] | None
    transitions: list[dict[str, Any]]


def _viewer_user(sessions: sessionmaker[DB], cookie: str | None, submission_id: int) -> User | None:
    """Who is watching, after checking they may see the submission (404 otherwise)."""
    with sessions() as db:
        session = accounts.session_for(db, cookie=cookie)
        user = session.user if session is not None else None
        get_visible(db, submission_id=submission_id, user=user)
        return user


def _poll(
    sessions: sessionmaker[DB], submission_id: int, after: int, user: User | None
) -> PolledSubmission | None:
    with sessions() as db:
        s = find_visible(db, submission_id=submission_id, user=user)
        if s is None:
            return None
        transitions = transitions_of(db, submission_id=submission_id, after=after)
        return PolledSubmission(
            state=s.state,
            reason=s.reason,
            score=s.score,
            progress=s.progress,
            transitions=[
                {
                    "id": t.id,
                    "attempt": t.attempt,
                    "from": t.from_state.value if t.from_state else None,
                    "to": t.to_state.value,
                    "reason": t.reason,
                    "at": t.at.isoformat(),
                    "at_text": f"{t.at:%Y-%m-%d %H:%M} UTC",
                }
                for t in transitions
            ],
        )


def sse(event: str, data: object, *, event_id: int | None = None) -> str:
    """One event in the text/event-stream format (JSON data on one line)."""
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


async def _stream(
    request: Request, submission_id: int, after: int, user: User | None, timing: StreamTiming
) -> AsyncIterator[str]:
    sessions = services(request).sessions
    feed: ChangeFeed = request.app.state.change_feed
    yield f"retry: {timing.retry_ms}\n\n"
    with feed.watch(submission_id) as signal:  # before the first read: no change falls between
        async for chunk in _follow(request, sessions, signal, submission_id, after, user, timing):
            yield chunk


async def _follow(
    request: Request,
    sessions: sessionmaker[DB],
    signal: asyncio.Event,
    submission_id: int,
    after: int,
    user: User | None,
    timing: StreamTiming,
) -> AsyncIterator[str]:
    started = last_sent = last_read = time.monotonic()
    last_progress: dict[str, Any] | None = None
    read = True
    while True:
        if read:  # the first time, on a change signal, and every `fallback_s` regardless
            signal.clear()
            snap = await run_in_threadpool(_poll, sessions, submission_id, after, user)
            last_read = time.monotonic()
            if snap is None:  # deleted, or no longer visible to this viewer
                yield sse("gone", {})
                return
            chunks = []
            for t in snap.transitions:
                chunks.append(sse("transition", t, event_id=t["id"]))
                after = t["id"]
            if snap.progress != last_progress and snap.state in (State.LAUNCHING, State.RUNNING):
                chunks.append(sse("progress", snap.progress or {}))
                last_progress = snap.progress
            if snap.state.final:
                chunks.append(sse("end", {"state": snap.state.value, "reason": snap.reason}))
            if chunks:
                yield "".join(chunks)
                last_sent = time.monotonic()
            if snap.state.final:
                return
        now = time.monotonic()
        if now - last_sent >= timing.keepalive_s:  # without a read: idle streams cost nothing
            yield ": keep-alive\n\n"
            last_sent = now
        if now - started >= timing.max_s or await request.is_disconnected():
            return
        wait = min(
            timing.fallback_s - (now - last_read),
            timing.keepalive_s - (now - last_sent),
            timing.max_s - (now - started),
        )
        try:
            await asyncio.wait_for(signal.wait(), timeout=max(wait, 0.0))
            read = True
        except TimeoutError:
            read = time.monotonic() - last_read >= timing.fallback_s


@router.get("/submissions/{submission_id}/events")
async def submission_events(
    submission_id: Id,
    request: Request,
    after: Annotated[int, Query(ge=0, le=2**62)] = 0,
) -> Response:
    """The live state of a submission (text/event-stream) for its page's script."""
    svc = services(request)
    user = await run_in_threadpool(
        _viewer_user, svc.sessions, request.cookies.get(SESSION_COOKIE), submission_id
    )
    resumed = request.headers.get("last-event-id", "")
    if resumed.isdigit() and len(resumed) < 19:
        after = max(after, int(resumed))
    timing: StreamTiming = request.app.state.event_timing
    slots: StreamSlots = request.app.state.event_slots
    client = request.client.host if request.client is not None else "unknown"
    if not slots.take(client):
        raise Unavailable("too many live views are open; the page will try again", retry_after=10)

    async def bounded() -> AsyncIterator[str]:
        try:
            async for chunk in _stream(request, submission_id, after, user, timing):
                yield chunk
        finally:
            slots.give_back(client)

    return StreamingResponse(
        bounded(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
    )
