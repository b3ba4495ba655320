"""Property-based API tests generated from `/openapi.json` (schemathesis), as a second user.

Alice owns a private submission, a public one with logs, and an API token; Bob is the caller.
Whatever Bob sends, the server must answer without a 5xx, within its documented schema, and
never with a byte of Alice's private data.
"""

from __future__ import annotations

import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from evaluator.results import (
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    SuiteRef,
    Versions,
    aggregate_task,
)
from server.accounts import service as accounts
from server.app import create_app
from server.challenges.service import ChallengeOptions, get_challenge, get_phase, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import State
from server.submissions.reports import report_final, report_state
from server.submissions.service import submit
from tests.factories import PASSWORD, SUITE, RecordingQueue, fake_resolve_for

SECRET = "ALICE-PRIVATE-3f9c"  # appears only in Alice's private data
_DATA = Path(tempfile.mkdtemp(prefix="manieval-schemathesis-"))


def _result() -> EvaluationResult:
    episodes = [
        EpisodeResult(
            index=0,
            seed=7,
            success_once=True,
            success_at_end=True,
            steps=5,
            episode_return=1.0,
            wall_time_s=0.1,
        )
    ]
    task = aggregate_task("PickCube-v1", 1, episodes)
    now = datetime.now(UTC)
    return EvaluationResult(
        suite=SuiteRef(name="server-tiny", version=1, sha256="0" * 64),
        phase="dev",
        policy="x",
        versions=Versions(manieval="0", mani_skill="0", sapien="0", torch="0", python="3"),
        started_at=now,
        finished_at=now,
        status="completed",
        score=1.0,
        conditions=[ConditionResult(name="nominal", params={}, score=1.0, tasks=[task])],
    )


def _build() -> tuple[Any, str]:
    s = Settings(
        dev_mode=True,
        data_dir=_DATA,
        cookie_secure=False,
        register_rate="10000/minute",
        login_rate="10000/minute",
        token_rate="10000/minute",
        submit_rate="10000/minute",
    )
    upgrade(s.resolved_database_url)
    sessions = session_factory(make_engine(s.resolved_database_url))
    resolve = fake_resolve_for(s)
    with sessions.begin() as db:
        load_challenge(
            db,
            SUITE,
            ChallengeOptions(quota_per_day=10_000, quota_concurrent=10_000),
            seed_secret=s.secret("seed_secret"),
        )
        alice = accounts.register(
            db, username="alice", email="alice@example.org", password=PASSWORD
        )
        bob = accounts.register(db, username="bob", email="bob@example.org", password=PASSWORD)
        accounts.create_token(db, user=alice, name=SECRET)
        challenge = get_challenge(db, slug="server-tiny")
        for public in (False, True):
            sub = submit(
                db,
                user=alice,
                challenge=challenge,
                phase=get_phase(challenge, "dev"),
                image=f"127.0.0.1:5000/alice/{'open' if public else 'hidden'}:v1",
                description=SECRET if not public else "public one",
                public=public,
                resolve=resolve,
            )
            db.flush()
            report_state(db, sub.id, 1, State.LAUNCHING, "x")
            report_state(db, sub.id, 1, State.RUNNING, "x")
            report_final(db, sub.id, 1, State.SUCCEEDED, "done", result=_result(), log_tail=SECRET)
        _, bob_token = accounts.create_token(db, user=bob, name="fuzz")
    app = create_app(
        s,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=resolve,
        limiter=MemoryRateLimiter(),
        background=False,
    )
    return app, bob_token


APP, BOB_TOKEN = _build()
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]


@schema.parametrize()
@settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_as_another_user(case: schemathesis.Case) -> None:
    response = case.call_and_validate(
        headers={"Authorization": f"Bearer {BOB_TOKEN}"}, checks=CHECKS
    )
    assert SECRET not in response.text, f"{case.method} {case.path} leaked Alice's data"


@schema.parametrize()
@settings(max_examples=5, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_anonymous(case: schemathesis.Case) -> None:
    response = case.call_and_validate(checks=CHECKS)
    assert SECRET not in response.text, f"{case.method} {case.path} leaked Alice's data"
