"""Fixtures every test folder shares: each database test runs on SQLite and on this machine's
Postgres, and `client` is the app on that database.

Each test runs inside a transaction that is rolled back afterwards (the app's own commits
become savepoints), so tests are independent and fast. Tests that need real concurrent
connections use `committed_sessions`, which truncates after the test instead. Plain helpers
(users, challenges, submissions, result documents) are in `tests/factories.py`.
"""

from __future__ import annotations

import gc
import os
import signal
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import hypothesis
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.db import make_engine, upgrade
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import Base
from testkit.factories import RecordingQueue, fake_resolve_for

# Property tests (and schemathesis) try the same examples on every run: what they find is a
# finding, never a coin toss in CI. `pytest --hypothesis-profile=explore` searches anew.
hypothesis.settings.register_profile("suite", derandomize=True, database=None, deadline=None)
hypothesis.settings.register_profile("explore", deadline=None)
hypothesis.settings.load_profile("suite")

PG_ADMIN_URL = os.environ.get(
    "MANIEVAL_TEST_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)


def pytest_configure(config: pytest.Config) -> None:
    foreground_signals()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Modules marked `long` first, in their order. `make test` gives whole modules to parallel
    workers (`--dist loadscope`, so a module's expensive fixtures are built once): the longest
    started first end with the rest, instead of one of them running alone at the end."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)  # stable


def foreground_signals() -> None:
    """SIGINT and SIGTERM as a terminal's foreground process has them, whatever started pytest.

    A background job of a non-interactive shell (`nohup make test &`, some CI runners) starts
    with SIGINT ignored, and an ignored signal stays ignored across `exec`: every process a test
    starts would inherit it. A handled signal is reset to its default in the child, so with these
    set here each child starts as from a terminal, and a test that signals one tests the code,
    not how pytest was launched. (tests/test_signals.py checks both sides.)
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_IGN:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


class _FreezeWatch:
    """Whether anything ran `gc.freeze` or `gc.unfreeze` since the last look: both are wrapped
    for the test process. (`gc.get_freeze_count()` cannot tell: it walks the whole frozen set,
    a million objects, about 0.1 s a call, and it also falls whenever a frozen object is freed.)"""

    def __init__(self) -> None:
        self.changed = False
        self.freeze, self.unfreeze = gc.freeze, gc.unfreeze

    def install(self) -> None:
        gc.freeze, gc.unfreeze = self._watched(self.freeze), self._watched(self.unfreeze)

    def _watched(self, call: Callable[[], None]) -> Callable[[], None]:
        def watched() -> None:
            self.changed = True
            call()

        return watched

    def refreeze(self) -> None:
        """Collect what is garbage, frozen or not, and freeze the rest."""
        self.unfreeze()
        gc.collect()
        self.freeze()
        self.changed = False


_freezes = _FreezeWatch()


def pytest_collection_finish(session: pytest.Session) -> None:
    """What the suite imported to collect its tests (the app and the libraries it uses) lives
    as long as the test process: exempt it from the cyclic garbage collector once, as the server
    and the evaluator do in production (`gc.freeze`). Otherwise every full collection in a test,
    ManiSkill's at each scene rebuild among them, walks all of it. (torch and ManiSkill come
    later, with a test's first environment; the evaluator freezes them then, and so does
    `_collectable_again` after that test.)"""
    _freezes.refreeze()
    _freezes.install()


@pytest.fixture(autouse=True)
def _collectable_again() -> Iterator[None]:
    """The server and the evaluator freeze what exists once per process (at the first app,
    after the first environment, after a large leaderboard read), and a test may unfreeze. In
    one test process apps and boards come and go by the hundred: after a test that froze or
    unfroze, what it left is collected and the rest frozen again, so nothing a test made stays
    exempt for good and what the suite imported stays exempt."""
    yield
    if _freezes.changed:
        _freezes.refreeze()


def _require(what: str, exc: Exception) -> None:
    message = f"{what} is not reachable: {exc}"
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    """A fresh, migrated database on the local Postgres, dropped after the session."""
    name = f"manieval_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"'))
    except Exception as exc:
        _require("Postgres", exc)
    url = PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"
    try:
        yield url
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture(scope="session")
def sqlite_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('db') / 'manieval.db'}"


@pytest.fixture(scope="session", params=["sqlite", "postgres"])
def engine(request: pytest.FixtureRequest) -> Iterator[Engine]:
    url = request.getfixturevalue(f"{request.param}_url")
    upgrade(url)
    eng = make_engine(url)
    yield eng
    eng.dispose()


@pytest.fixture
def sessions(engine: Engine) -> Iterator[sessionmaker[Session]]:
    """Sessions inside one outer transaction, rolled back after the test."""
    connection = engine.connect()
    outer = connection.begin()
    try:
        yield sessionmaker(
            bind=connection, join_transaction_mode="create_savepoint", expire_on_commit=False
        )
    finally:
        outer.rollback()
        connection.close()


@pytest.fixture
def committed_sessions(engine: Engine) -> Iterator[sessionmaker[Session]]:
    """Real commits on separate connections (for races); every table is emptied after."""
    yield sessionmaker(engine, expire_on_commit=False)
    with engine.begin() as conn:
        for table in reversed(Base.metadata.sorted_tables):
            conn.execute(table.delete())


@pytest.fixture
def db(sessions: sessionmaker[Session]) -> Iterator[Session]:
    with sessions() as session:
        yield session


# The app ---------------------------------------------------------------------------------------


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(
        dev_mode=True,
        data_dir=tmp_path,
        cookie_secure=False,
        allow_local_policies=True,
        register_rate="1000/minute",
        login_rate="1000/minute",
        token_rate="1000/minute",
        submit_rate="1000/minute",
        leaderboard_max_age=0,  # tests read their writes at once
    )


@pytest.fixture
def work() -> RecordingQueue:
    return RecordingQueue()


@pytest.fixture
def client(
    settings: Settings, sessions: sessionmaker[Session], work: RecordingQueue
) -> Iterator[TestClient]:
    app = create_app(
        settings,
        sessions=sessions,
        work=work,
        resolve=fake_resolve_for(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app, base_url="http://testserver") as c:
        yield c
