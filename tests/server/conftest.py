"""Server test fixtures: every database test runs on SQLite and on this machine's Postgres.

Each test runs inside a transaction that is rolled back afterwards (the app's own commits
become savepoints), so tests are independent and fast. Tests that need real concurrent
connections use `committed_sessions`, which truncates after the test instead.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.orm import Session, sessionmaker

from evaluator.results import (
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    SuiteRef,
    Versions,
    aggregate_task,
)
from server import accounts
from server.app import create_app, image_resolver
from server.challenges import ChallengeOptions, load_challenge
from server.db import make_engine, session_factory, upgrade
from server.image_refs import ImageReference, ResolvedImage
from server.models import Base, Challenge, Submission, User
from server.ratelimit import MemoryRateLimiter
from server.settings import Settings
from server.submissions import Resolved, Resolver, submit

PG_ADMIN_URL = os.environ.get(
    "MANIEVAL_TEST_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)
SUITE = Path(__file__).resolve().parent / "server_suite.yaml"
PASSWORD = "correct horse battery staple"


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


# Factories -----------------------------------------------------------------------------------


def make_user(db: Session, username: str, *, admin: bool = False) -> User:
    user = accounts.register(
        db, username=username, email=f"{username}@example.org", password=PASSWORD, admin=admin
    )
    db.commit()
    return user


def make_challenge(db: Session, **options: object) -> Challenge:
    challenge = load_challenge(
        db,
        SUITE,
        ChallengeOptions(**options),
        seed_secret="s" * 32,  # type: ignore[arg-type]
    )
    db.commit()
    return challenge


def embedded_database(settings: Settings, **options: object) -> sessionmaker[Session]:
    """A migrated database for `settings` with two challenges: `server-tiny`, and
    `server-long` (200 episodes of 100 steps: long enough to cancel or kill a run mid-way)."""
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    long_suite = settings.data_dir / "server-long.yaml"
    long_suite.write_text(
        SUITE.read_text()
        .replace("name: server-tiny", "name: server-long")
        .replace("max_episode_steps: 12, episodes: 2", "max_episode_steps: 100, episodes: 200")
    )
    with sessions.begin() as db:
        for suite in (SUITE, long_suite):
            load_challenge(
                db,
                suite,
                ChallengeOptions(**options),  # type: ignore[arg-type]
                seed_secret=settings.secret("seed_secret"),
            )
    return sessions


def queue_submission(
    db: Session, user: User, challenge: Challenge, phase: str = "dev"
) -> Submission:
    """A queued submission through the real submit path, with a stand-in pinned image."""
    target = next(p for p in challenge.phases if p.name == phase)
    return submit(
        db,
        user,
        challenge,
        target,
        image="x",
        description="",
        public=True,
        resolve=lambda _image: Resolved(pinned="x@sha256:" + "0" * 64, size_bytes=1),
    )


def result_doc(
    successes: list[bool], *, phase: str = "dev", conditions: tuple[str, ...] = ("nominal",)
) -> EvaluationResult:
    """A completed result of PickCube-v1 on the server-tiny suite: these episode outcomes,
    the same task under every condition."""
    episodes = [
        EpisodeResult(
            index=i,
            seed=1000 + i,
            success_once=ok,
            success_at_end=ok,
            steps=10,
            episode_return=1.0,
            wall_time_s=0.1,
        )
        for i, ok in enumerate(successes)
    ]
    task = aggregate_task("PickCube-v1", len(episodes), episodes)
    now = datetime.now(UTC)
    return EvaluationResult(
        suite=SuiteRef(name="server-tiny", version=1, sha256="0" * 64),
        phase=phase,
        policy="test",
        versions=Versions(manieval="0", mani_skill="0", sapien="0", torch="0", python="3"),
        started_at=now,
        finished_at=now,
        status="completed",
        score=task.success_rate,
        conditions=[
            ConditionResult(name=name, params={"kind": name}, score=task.success_rate, tasks=[task])
            for name in conditions
        ],
    )


# The app ---------------------------------------------------------------------------------------


@dataclass
class RecordingQueue:
    sent: list[tuple[int, int]] = field(default_factory=list)

    def enqueue(self, submission_id: int, attempt: int) -> None:
        self.sent.append((submission_id, attempt))


class FakeRegistry:
    """Stands in for the registry where a test is not about it (the real one is tested in
    test_images.py and test_submit_registry.py); reference parsing is the real one."""

    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage:
        digest = "sha256:" + uuid.uuid5(uuid.NAMESPACE_URL, str(ref)).hex * 2
        return ResolvedImage(
            reference=ref, digest=digest, size_bytes=1234, pinned=ref.pinned(digest)
        )


def fake_resolve_for(settings: Settings) -> Resolver:
    return image_resolver(settings, FakeRegistry())


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


def token_for(client: TestClient, username: str) -> dict[str, str]:
    """Log in by password and return Authorization headers with a fresh API token."""
    r = client.post("/api/v1/auth/token", json={"login": username, "password": PASSWORD})
    assert r.status_code == 201, r.text
    return {"Authorization": f"Bearer {r.json()['token']}"}
