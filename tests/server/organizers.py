"""What the organizer tests share: a challenge with room to submit, two participants and an
admin ("judge"), and their API tokens."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server.models import Challenge, User
from testkit.factories import make_challenge, make_user, token_for

API = "/api/v1"


@pytest.fixture(name="tiny")
def fixture_tiny(db: Session) -> Challenge:
    return make_challenge(db, quota_per_day=20, quota_concurrent=5)


@pytest.fixture(name="people")
def fixture_people(client: TestClient, db: Session) -> dict[str, User]:
    found = {name: make_user(db, name) for name in ("alice", "bob")}
    return found | {"judge": make_user(db, "judge", admin=True)}


@pytest.fixture(name="tokens")
def fixture_tokens(client: TestClient, people: dict[str, User]) -> dict[str, dict[str, str]]:
    return {name: token_for(client, name) for name in people}
