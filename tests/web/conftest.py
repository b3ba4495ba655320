"""Web tests share the server's fixtures: the app on SQLite and Postgres, rolled back."""

from __future__ import annotations

import pytest
from sqlalchemy.orm import Session

from server.models import Challenge
from tests.server.conftest import (  # noqa: F401 - pytest fixtures
    client,
    committed_sessions,
    db,
    engine,
    make_challenge,
    postgres_url,
    sessions,
    settings,
    sqlite_url,
    work,
)


@pytest.fixture
def tiny(db: Session) -> Challenge:  # noqa: F811 - the fixture above
    """The small server test challenge: 3 submissions a day, 2 at once."""
    return make_challenge(db, quota_per_day=3, quota_concurrent=2)
