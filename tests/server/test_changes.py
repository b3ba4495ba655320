"""Live views are told when their submission changes: after a commit, never on a rollback,
across processes through Postgres LISTEN/NOTIFY, in the process itself on SQLite."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time

from sqlalchemy import text
from sqlalchemy.orm import Session, sessionmaker

from server.submissions.changes import ChangeFeed, _payloads, changed
from tests.evaluator.conftest import REPO

SIGNAL_S = 60.0  # a generous bound on a signal's arrival on a busy machine


async def signalled(signal: asyncio.Event, timeout: float = SIGNAL_S) -> bool:
    try:
        await asyncio.wait_for(signal.wait(), timeout)
    except TimeoutError:
        return False
    return True


def test_a_commit_wakes_the_views_of_the_changed_submissions_only(
    committed_sessions: sessionmaker[Session],
) -> None:
    feed = ChangeFeed()

    async def scenario() -> tuple[bool, bool, bool]:
        with feed.watch(1) as one, feed.watch(2) as two:
            with committed_sessions.begin() as db:
                changed(db, 1)
                assert not one.is_set()  # not before the commit
            woke = await signalled(one)
            return woke, two.is_set(), feed.watched == 2

    assert asyncio.run(scenario()) == (True, False, True)
    assert feed.watched == 0


def test_a_rollback_wakes_nobody(committed_sessions: sessionmaker[Session]) -> None:
    feed = ChangeFeed()

    async def scenario() -> bool:
        with feed.watch(3) as three:
            with committed_sessions() as db:
                db.execute(text("SELECT 1"))  # as the change it would signal
                changed(db, 3)
                db.rollback()
                db.commit()  # a later commit of the same session carries no stale signal
            return await signalled(three, timeout=0.5)

    assert asyncio.run(scenario()) is False


def test_a_change_committed_by_another_process_arrives_through_postgres(
    postgres_url: str,
) -> None:
    feed = ChangeFeed()
    feed.listen(postgres_url)
    code = (
        "import sys\n"
        "from sqlalchemy.orm import sessionmaker\n"
        "from server.kit.db import make_engine\n"
        "from server.submissions.changes import changed\n"
        "with sessionmaker(make_engine(sys.argv[1])).begin() as db:\n"
        "    changed(db, 4242)\n"
    )

    async def scenario() -> bool:
        with feed.watch(4242) as signal:
            deadline = time.monotonic() + SIGNAL_S
            while time.monotonic() < deadline:  # until the listener has connected
                subprocess.run([sys.executable, "-c", code, postgres_url], cwd=REPO, check=True)
                if await signalled(signal, timeout=1.0):
                    return True
            return False

    try:
        assert asyncio.run(scenario())
    finally:
        feed.close()


def test_many_changes_fit_in_notify_payloads() -> None:
    payloads = list(_payloads(set(range(1, 5000))))
    assert len(payloads) > 1
    assert all(len(p.encode()) < 8000 for p in payloads)
    assert sorted(int(i) for p in payloads for i in p.split(",")) == list(range(1, 5000))
