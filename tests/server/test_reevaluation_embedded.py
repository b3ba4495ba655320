"""Re-evaluation end to end on Postgres (issue 27's acceptance): real evaluations of the tiny
suite by the embedded worker (the real worker code reaching the app in-process through
`/internal/v1`), a suite version bump, `manieval challenge reevaluate`, and then a new board
version while the old one is still served and nobody's quota moved."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from manieval.cli import app as cli
from manieval.service import EMBEDDED_WORKER
from server.app import create_app
from server.challenges.quota import QuotaUse, quota_use
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.settings import Settings
from server.models import Base, Challenge, Phase, Submission, User, utcnow
from testkit.factories import PASSWORD, SUITE, embedded_database, token_for
from testkit.waiting import until
from testkit.workers import server_api, worker_settings
from worker.embedded import EmbeddedWorker

API = "/api/v1"
BOARD = f"{API}/challenges/server-tiny/leaderboard"
OPTIONS = {"quota_per_day": 2, "quota_concurrent": 1}
pytestmark = [pytest.mark.sim, pytest.mark.long]


@pytest.fixture
def settings(tmp_path: Path, postgres_url: str) -> Settings:
    return Settings(
        dev_mode=True,
        data_dir=tmp_path,
        cookie_secure=False,
        allow_local_policies=True,
        database_url=postgres_url,
        leaderboard_max_age=0,
    )


@pytest.fixture
def sessions(settings: Settings) -> Iterator[sessionmaker[Session]]:
    made = embedded_database(settings, **OPTIONS)
    yield made
    engine = made.kw["bind"]
    with engine.begin() as conn:  # the session's database is shared: leave it empty
        for table in reversed(Base.metadata.sorted_tables):
            conn.execute(table.delete())
    engine.dispose()


def ended(sessions: sessionmaker[Session], ids: list[int]) -> list[Submission] | None:
    with sessions() as db:
        found = db.scalars(select(Submission).where(Submission.id.in_(ids))).all()
        return list(found) if all(s.state.final for s in found) else None


def quotas(sessions: sessionmaker[Session]) -> dict[str, QuotaUse]:
    now = utcnow()
    with sessions() as db:
        challenge = db.scalar(select(Challenge).where(Challenge.slug == "server-tiny"))
        assert challenge is not None
        users = db.scalars(select(User).where(User.username.in_(["alice", "bob"]))).all()
        return {u.username: quota_use(db, user=u, challenge=challenge, now=now) for u in users}


def ids_on(client: TestClient, **params: Any) -> set[int]:
    r = client.get(BOARD, params={"phase": "dev", **params})
    assert r.status_code == 200, r.text
    return {row["submission_id"] for row in r.json()["items"]}


def test_reevaluate_after_a_suite_version_bump_makes_a_new_board_version_and_keeps_the_old(
    settings: Settings,
    sessions: sessionmaker[Session],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    wsettings = worker_settings(settings, worker_name=EMBEDDED_WORKER)
    worker = EmbeddedWorker(wsettings)
    app = create_app(settings, sessions=sessions, work=worker.queue)
    api = server_api(app, wsettings)
    with TestClient(app) as client:
        try:
            worker.start(api=api)
            originals = []
            for name, policy in (("alice", "local:scripted"), ("bob", "local:random")):
                client.post(
                    f"{API}/users",
                    json={"username": name, "email": f"{name}@example.org", "password": PASSWORD},
                ).raise_for_status()
                r = client.post(
                    f"{API}/submissions",
                    headers=token_for(client, name),
                    json={"challenge": "server-tiny", "image": policy},
                )
                assert r.status_code == 202, r.text
                originals.append(r.json()["id"])
            first = until(lambda: ended(sessions, originals), "the submissions to end", timeout=300)
            assert {s.state.value for s in first} == {"succeeded"}
            assert ids_on(client) == set(originals)
            before = quotas(sessions)

            bumped = tmp_path / "server-tiny-v2.yaml"  # the organizer fixes the suite
            bumped.write_text(SUITE.read_text().replace("version: 1", "version: 2", 1))
            with sessions.begin() as db:
                load_challenge(
                    db,
                    bumped,
                    ChallengeOptions(**OPTIONS),
                    seed_secret=settings.secret("seed_secret"),
                )
            monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
            monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
            monkeypatch.setenv("MANIEVAL_DATABASE_URL", settings.resolved_database_url)
            done = CliRunner().invoke(
                cli, ["challenge", "reevaluate", "server-tiny", "--phase", "dev"]
            )
            assert done.exit_code == 0, done.output
            assert "2 entries queued for board version 2" in done.output
            app.state.services.dispatcher.dispatch()  # the command's work, to the worker
            with sessions() as db:
                copies = db.scalars(
                    select(Submission.id).where(Submission.reevaluation_of.in_(originals))
                ).all()
            assert len(copies) == 2
            again = until(lambda: ended(sessions, list(copies)), "the re-runs to end", timeout=300)
            assert {s.state.value for s in again} == {"succeeded"}

            with sessions() as db:
                version = select(Phase.board_version).join(Challenge)
                version = version.where(Challenge.slug == "server-tiny", Phase.name == "dev")
                assert db.scalar(version) == 2
                assert {s.result["suite"]["version"] for s in again if s.result} == {2}
            assert ids_on(client) == set(copies)  # the new version is the board
            assert ids_on(client, version=2) == set(copies)
            assert ids_on(client, version=1) == set(originals)  # the old one is still served
            page = client.get("/challenges/server-tiny/leaderboard?phase=dev&version=1").text
            assert all(f'/submissions/{sid}"' in page for sid in originals)
            assert quotas(sessions) == before  # quotas untouched
            shown = client.get(f"/submissions/{originals[0]}").text
            assert "Evaluations on each board version" in shown
            assert "version 1, " in shown
            assert "version 2, " in shown
        finally:
            worker.stop(timeout=60)
            api.close()
