"""Property-based API tests generated from `/openapi.json` (schemathesis), on SQLite and on this
machine's Postgres (issue 13: a NUL gave 500 on Postgres only), as two users and anonymously,
request by request and then in sequences (schemathesis's stateful phase, whose links it infers
from the responses and path parameters).

Alice owns a private submission, a public one with logs, and an API token; Bob is the other
user. Whatever anyone sends, the server must answer without a 5xx and within its documented
schema, and Bob and anonymous callers never see a byte of Alice's private data.

Each case is drawn once and sent to both servers (issue 25: drawing costs more than answering):
the same seeded server is built on each database, the cases are drawn from SQLite's
`/openapi.json` (Postgres's must be the same document), and every drawn case goes to the SQLite
server and then to the Postgres one, as the caller's own token on each, each answer under the
same checks; a failure says which database answered. A sequence is driven by SQLite's answers
(the links it follows, and so its next steps, come from them) and each of its steps is replayed
on Postgres, both servers restored to the seeded state at each scenario's start, so the ids the
links carry are the same on both. The answers need not be equal (timestamps, tokens differ),
only each within the checks. Where Postgres is not reachable the cases go to SQLite alone, with
a warning (on CI, where CI=true, that fails instead).

Bounded for a 2-core CI machine: a few examples per operation and short sequences. The tests
request by request are split by the operation's first OpenAPI tag, so a failure names the part
of the API, and one test checks that every operation has one of those tags.
"""

from __future__ import annotations

import os
import re
import tempfile
import uuid
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.core.failures import FailureGroup
from schemathesis.generation.jsonschema import strategy as jsonschema_strategy
from schemathesis.generation.stateful.state_machine import StepInput, StepOutput
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from sqlalchemy import Engine, create_engine, text, update

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
from server.models import Phase, State
from server.models.base import Base
from server.submissions.reports import report_final, report_state
from server.submissions.service import submit
from testkit.factories import PASSWORD, SUITE, RecordingQueue, fake_resolve_for

pytestmark = pytest.mark.long


@pytest.fixture(scope="module", autouse=True)
def _pattern_strategies_built_once() -> Iterator[None]:
    """Build each pattern's string strategy once per module, not once per test and operation.

    schemathesis builds a field's strategy anew for every operation in every test; for our
    printable-text patterns (negated classes that span Unicode: `[^\x00-\x1f\ud800-...]*`)
    `from_regex` with the codec's alphabet takes about a second each time, and that was 40 % of
    this module's time. A strategy is an immutable description of values, safe to draw from
    in any test, and its inputs here are the pattern and the alphabet, so it is cached on those,
    as schemathesis already caches `_anything_for` on the alphabet. What is generated does not
    change."""
    built: dict[tuple[str, int, Any], Any] = {}
    original = jsonschema_strategy._from_pattern

    def from_pattern(compiled: re.Pattern[str], ctx: Any) -> Any:
        key = (compiled.pattern, compiled.flags, ctx.alphabet)
        if key not in built:
            built[key] = original(compiled, ctx)
        return built[key]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(jsonschema_strategy, "_from_pattern", from_pattern)
        yield


SECRET = "ALICE-PRIVATE-3f9c"  # appears only in Alice's private data
PG_ADMIN_URL = os.environ.get(
    "MANIEVAL_TEST_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]
# Invalid input may be answered with any documented error, but never a 5xx or a body outside
# the schema.
NEGATIVE = [not_a_server_error, content_type_conformance, response_schema_conformance]
STATEFUL = settings(
    max_examples=25,
    stateful_step_count=6,
    deadline=None,
    suppress_health_check=list(HealthCheck),
)


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


@dataclass
class World:
    app: Any
    headers: dict[str, dict[str, str]]  # "alice", "bob", "anonymous"
    engine: Engine
    snapshot: dict[str, list[dict[str, Any]]]
    restores: int = 0

    def restore(self) -> None:
        """Every table as it was after seeding. A stateful scenario's choices depend on the
        answers it got (a submission Bob made, a token Alice revoked): replayed against a
        server that kept the earlier scenarios' changes, the same choices would meet other
        answers, and Hypothesis would rightly call the generation flaky."""
        self.restores += 1
        tables = Base.metadata.sorted_tables
        with self.engine.begin() as conn:
            for table in reversed(tables):
                conn.execute(table.delete())
            for table in tables:
                if rows := self.snapshot[table.name]:
                    conn.execute(table.insert(), rows)
            if conn.dialect.name == "postgresql":  # new rows get the same ids as before
                for table in tables:
                    if "id" in table.c:
                        conn.execute(
                            text(
                                f"SELECT setval(pg_get_serial_sequence('{table.name}', 'id'), "
                                f"coalesce(max(id), 0) + 1, false) FROM {table.name}"
                            )
                        )
            # Boards cached for a version number the restore brings back would be stale.
            conn.execute(
                update(Phase).values(
                    leaderboard_version=Phase.leaderboard_version + 1000 * self.restores
                )
            )


def _snapshot(engine: Engine) -> dict[str, list[dict[str, Any]]]:
    with engine.connect() as conn:
        return {
            table.name: [dict(row._mapping) for row in conn.execute(table.select())]
            for table in Base.metadata.sorted_tables
        }


def _build(database_url: str, data_dir: Path) -> World:
    s = Settings(
        dev_mode=True,
        data_dir=data_dir,
        database_url=database_url,
        cookie_secure=False,
        register_rate="10000/minute",
        login_rate="10000/minute",
        token_rate="10000/minute",
        submit_rate="10000/minute",
        login_failures_per_address="10000/minute",
        login_failures_per_account_address="10000/minute",
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
        _, alice_token = accounts.create_token(db, user=alice, name="fuzz")
        _, bob_token = accounts.create_token(db, user=bob, name="fuzz")
    app = create_app(
        s,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=resolve,
        limiter=MemoryRateLimiter(),
        background=False,
    )
    engine = make_engine(s.resolved_database_url)
    return World(
        app=app,
        headers={
            "alice": {"Authorization": f"Bearer {alice_token}"},
            "bob": {"Authorization": f"Bearer {bob_token}"},
            "anonymous": {},
        },
        engine=engine,
        snapshot=_snapshot(engine),
    )


@pytest.fixture(scope="module")
def fuzz_postgres_url() -> Iterator[str | None]:
    """A database of its own on the local Postgres: the fuzzing commits, unlike other tests.
    None where Postgres is not reachable, outside CI (on CI that fails)."""
    name = f"manieval_fuzz_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"'))
    except Exception as exc:  # any failure to reach Postgres: SQLite alone, or fail on CI
        admin.dispose()
        message = f"Postgres is not reachable: {exc}"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        warnings.warn(f"{message}: the API is fuzzed on SQLite alone", stacklevel=1)
        yield None
        return
    try:
        yield PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


DRIVER = "sqlite"
"""The database whose server the cases are drawn from and whose answers drive the sequences:
the one every machine has."""


@pytest.fixture(scope="module")
def worlds(fuzz_postgres_url: str | None) -> dict[str, World]:
    """The same seeded server on each database, SQLite first: each drawn case goes to all."""
    urls: dict[str, str | None] = {DRIVER: None, "postgres": fuzz_postgres_url}
    built = {}
    for database, url in urls.items():
        data_dir = Path(tempfile.mkdtemp(prefix="manieval-schemathesis-"))
        if database == DRIVER:
            url = f"sqlite:///{data_dir / 'manieval.db'}"
        if url is not None:
            built[database] = _build(url, data_dir)
    return built


CALL_TIMEOUT_S = 300
"""How long one call (the schema's load included) may take before it counts as hung:
schemathesis's default (10 s) is a guess about an idle machine; a busy one took longer to
answer GET /team on Postgres, and to build /openapi.json."""


@pytest.fixture(scope="module")
def api_schema(worlds: dict[str, World]) -> Any:
    """The schema the cases are drawn from: the driver's, which every server must serve."""
    document = worlds[DRIVER].app.openapi()
    for database, world in worlds.items():
        assert world.app.openapi() == document, f"{database} serves another /openapi.json"
    return schemathesis.openapi.from_asgi(
        "/openapi.json", worlds[DRIVER].app, timeout=CALL_TIMEOUT_S
    )


TAGS = ("accounts", "challenges", "submissions", "admin", "teams", "registry")
"""The groups of the tests request by request: an operation's first OpenAPI tag."""


@pytest.fixture(scope="module")
def operations(api_schema: Any) -> list[Any]:
    return [result.ok() for result in api_schema.get_all_operations()]


def _group(operation: Any) -> str | None:
    return (operation.tags or [None])[0]


def test_every_operation_is_in_a_group(operations: list[Any]) -> None:
    assert not [op.label for op in operations if _group(op) not in TAGS], "add its tag to TAGS"


def _no_leak(response: Any, case: schemathesis.Case) -> None:
    assert SECRET not in response.text, f"{case.method} {case.path} leaked Alice's data"


@contextmanager
def _answered_by(database: str) -> Iterator[None]:
    """A failure inside says which database's server gave the answer it is about."""
    try:
        yield
    except (Exception, FailureGroup) as exc:
        exc.add_note(f"The {database} server's answer (the same case goes to {DRIVER} first).")
        raise


def _send_to_each(
    case: schemathesis.Case, worlds: dict[str, World], caller: str, checks: list[Any]
) -> dict[str, Any]:
    """The one drawn case to each database's server, as the caller (their token there), each
    answer under the same checks and, for anyone but Alice, the leak check."""
    answers = {}
    for database, world in worlds.items():
        with _answered_by(database):
            response = case.call(
                app=world.app, headers=world.headers[caller], timeout=CALL_TIMEOUT_S
            )
            case.validate_response(response, checks=checks)
            if caller != "alice":
                _no_leak(response, case)
        answers[database] = response
    return answers


# Each operation in turn, driven by Hypothesis here rather than by `schema.parametrize()`: the
# schema comes from a fixture (the servers built for the module), and schemathesis's lazy fixture
# loader does not run on this pytest.
@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
@pytest.mark.parametrize(("caller", "examples"), [("alice", 10), ("bob", 15), ("anonymous", 8)])
@pytest.mark.parametrize("tag", TAGS)
def test_api_operation_by_operation(
    operations: list[Any],
    worlds: dict[str, World],
    tag: str,
    caller: str,
    examples: int,
    mode: GenerationMode,
) -> None:
    tagged = [operation for operation in operations if _group(operation) == tag]
    assert tagged, f"no operation's first tag is {tag}"
    for operation in tagged:

        @given(case=operation.as_strategy(generation_mode=mode))
        @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck))
        def check(case: schemathesis.Case) -> None:
            _send_to_each(case, worlds, caller, CHECKS if mode.is_positive else NEGATIVE)

        try:
            check()
        except Unsatisfiable:
            assert not mode.is_positive, operation.label  # nothing in it can be made invalid


def _run_stateful(api_schema: Any, worlds: dict[str, World], caller: str) -> None:
    machine: Any = api_schema.as_state_machine()

    class Scenario(machine):  # type: ignore[misc, valid-type]
        def setup(self) -> None:
            for world in worlds.values():  # each scenario starts from the same servers
                world.restore()

        def step(self, input: StepInput) -> StepOutput:
            """The step's case to every server; the driver's answer is what the machine
            follows (its links, its next steps)."""
            self.before_call(input.case)
            response = _send_to_each(input.case, worlds, caller, CHECKS)[DRIVER]
            self.after_call(response, input.case)
            return StepOutput(response, input.case)

    Scenario.run(settings=STATEFUL)


@pytest.mark.parametrize("caller", ["alice", "bob", "anonymous"])
def test_api_sequences(api_schema: Any, worlds: dict[str, World], caller: str) -> None:
    _run_stateful(api_schema, worlds, caller)
