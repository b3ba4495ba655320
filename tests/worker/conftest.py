"""Worker tests: the database fixtures are shared (tests/conftest.py); a worker reaches the
server under test through its internal API (`tests/workers.py`)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy.orm import Session, sessionmaker

from server.kit.settings import Settings
from testkit.factories import RecordingQueue
from testkit.workers import server_api, server_app, worker_settings
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings


@pytest.fixture
def wsettings(settings: Settings) -> WorkerSettings:
    return worker_settings(settings)


@pytest.fixture
def api(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    wsettings: WorkerSettings,
    work: RecordingQueue,
) -> Iterator[ServerAPI]:
    client = server_api(server_app(settings, committed_sessions, work), wsettings)
    yield client
    client.close()
