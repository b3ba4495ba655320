"""Telling open live views that a submission changed, instead of each one polling.

Code that changes a submission's state, progress or visibility calls `changed(db, id)`. When
that transaction commits (never on a rollback):
- on Postgres, a `NOTIFY manieval_submission, '<id>,...'` goes out with the commit, to every
  server process that listens (`ChangeFeed.listen`, one connection per process), its own
  included: so a change made by any process, API replica or operator command, wakes the views
  of every process;
- in this process, every `ChangeFeed` is told directly (all there is on SQLite, where the
  embedded server is one process).
A view (`server/submissions/events.py`) waits on its submission's signal, then reads the
database once; a rare missed signal (a listener reconnecting) costs at most the view's
fallback interval, after which it reads anyway.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import weakref
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

from sqlalchemy import event, text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, SessionTransaction

log = logging.getLogger(__name__)

CHANNEL = "manieval_submission"
_PENDING = "manieval_changed_submissions"
_PAYLOAD_LIMIT = 7900  # bytes; Postgres refuses a NOTIFY payload of 8000 or more
_LISTEN_RETRY_S = 2.0


def changed(db: Session, submission_id: int) -> None:
    """Mark a submission changed: its live views are woken once `db` commits."""
    db.info.setdefault(_PENDING, set()).add(submission_id)


class ChangeFeed:
    """One process's view of which submissions changed: waits, signals and the listener."""

    def __init__(self) -> None:
        self._watchers: dict[int, set[tuple[asyncio.AbstractEventLoop, asyncio.Event]]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._listener: threading.Thread | None = None
        _FEEDS.add(self)

    @contextmanager
    def watch(self, submission_id: int) -> Iterator[asyncio.Event]:
        """An event set whenever the submission changes, for as long as the block runs
        (registered before the caller's first read, so no change falls between)."""
        key = (asyncio.get_running_loop(), asyncio.Event())
        with self._lock:
            self._watchers.setdefault(submission_id, set()).add(key)
        try:
            yield key[1]
        finally:
            with self._lock:
                watchers = self._watchers.get(submission_id, set())
                watchers.discard(key)
                if not watchers:
                    self._watchers.pop(submission_id, None)

    def publish(self, submission_ids: Iterable[int]) -> None:
        """Wake the views of these submissions (from any thread)."""
        with self._lock:
            woken = [w for sid in submission_ids for w in self._watchers.get(sid, ())]
        for loop, signal in woken:
            try:
                loop.call_soon_threadsafe(signal.set)
            except RuntimeError:  # that loop has closed: its view is gone
                pass

    @property
    def watched(self) -> int:
        """How many views are waiting (for monitoring and tests)."""
        with self._lock:
            return sum(len(w) for w in self._watchers.values())

    @property
    def listening(self) -> bool:
        """Whether this feed follows Postgres notifications (`listen`)."""
        return self._listener is not None

    def listen(self, database_url: str) -> None:
        """On Postgres, follow other processes' changes through LISTEN (a thread and one
        connection, reconnecting after failures); elsewhere nothing is needed."""
        url = make_url(database_url)
        if url.get_backend_name() != "postgresql" or self._listener is not None:
            return
        dsn = url.set(drivername="postgresql").render_as_string(hide_password=False)
        self._listener = threading.Thread(
            target=self._listen, args=(dsn,), name="manieval-changes", daemon=True
        )
        self._listener.start()

    def close(self) -> None:
        """Stop listening (the thread notices within a second)."""
        self._stop.set()
        if self._listener is not None:
            self._listener.join(timeout=5)

    def _listen(self, dsn: str) -> None:
        import psycopg

        while not self._stop.is_set():
            try:
                with psycopg.connect(dsn, autocommit=True, connect_timeout=10) as conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    log.debug("listening for submission changes")
                    with self._lock:  # what changed while no one listened: read it again
                        missed = list(self._watchers)
                    self.publish(missed)
                    while not self._stop.is_set():
                        for notice in conn.notifies(timeout=1.0):
                            self.publish(_ids(notice.payload))
            except Exception as exc:  # the database restarting: views fall back to reading
                log.warning("listening for submission changes failed (%s); retrying", exc)
                self._stop.wait(_LISTEN_RETRY_S)


_FEEDS: weakref.WeakSet[ChangeFeed] = weakref.WeakSet()


def _ids(payload: str) -> list[int]:
    return [int(part) for part in payload.split(",") if part.isdigit()]


def _payloads(ids: set[int]) -> Iterator[str]:
    """The ids as comma-separated payloads, each under Postgres's limit."""
    chunk: list[str] = []
    size = 0
    for sid in sorted(ids):
        part = str(sid)
        if chunk and size + len(part) + 1 > _PAYLOAD_LIMIT:
            yield ",".join(chunk)
            chunk, size = [], 0
        chunk.append(part)
        size += len(part) + 1
    if chunk:
        yield ",".join(chunk)


@event.listens_for(Session, "before_commit")
def _notify(session: Session) -> None:
    ids: set[int] | None = session.info.get(_PENDING)
    if not ids or session.get_bind().dialect.name != "postgresql":
        return
    for payload in _payloads(ids):  # sent by Postgres with the commit, dropped on rollback
        notify = text("SELECT pg_notify(:channel, :payload)")
        session.execute(notify, {"channel": CHANNEL, "payload": payload})


@event.listens_for(Session, "after_commit")
def _published(session: Session) -> None:
    ids: set[int] | None = session.info.pop(_PENDING, None)
    if not ids:
        return
    notified = session.get_bind().dialect.name == "postgresql"
    for feed in list(_FEEDS):
        if notified and feed.listening:
            continue  # the NOTIFY sent with the commit reaches it: one wake, not two
        feed.publish(ids)


@event.listens_for(Session, "after_soft_rollback")
def _forgotten(session: Session, previous: SessionTransaction) -> None:
    if previous.parent is None:  # the whole transaction; a savepoint's leaves a spare signal
        session.info.pop(_PENDING, None)
