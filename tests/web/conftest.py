"""Web tests use the shared fixtures of `tests/conftest.py` (the app on SQLite and Postgres, rolled
back) and a challenge with a small quota."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from sqlalchemy.orm import Session

from server.models import Challenge
from testkit.factories import make_challenge


@pytest.fixture
def tiny(db: Session) -> Challenge:
    """The small server test challenge: 3 submissions a day, 2 at once."""
    return make_challenge(db, quota_per_day=3, quota_concurrent=2)


@pytest.fixture
def artefacts(tmp_path: Path) -> Path:
    """Where browser tests put their screenshots: $MANIEVAL_ARTEFACTS/web (kept, for
    docs/screenshots), or the test's own temporary directory."""
    root = os.environ.get("MANIEVAL_ARTEFACTS")
    path = Path(root) / "web" if root else tmp_path / "screenshots"
    path.mkdir(parents=True, exist_ok=True)
    return path
