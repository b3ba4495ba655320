"""Web tests use the shared fixtures of `tests/conftest.py` (the app on SQLite and Postgres, rolled
back) and a challenge with a small quota."""

from __future__ import annotations

import pytest
from sqlalchemy.orm import Session

from server.models import Challenge
from tests.factories import make_challenge


@pytest.fixture
def tiny(db: Session) -> Challenge:
    """The small server test challenge: 3 submissions a day, 2 at once."""
    return make_challenge(db, quota_per_day=3, quota_concurrent=2)
