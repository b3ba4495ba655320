"""Database outages: nothing finished is lost, no wake-up is dropped, submits are told 503.

A private Postgres that the test stops and starts (`pg_ctl -m fast`: connections are cut, as
in a real restart) behind a real server (uvicorn, the Celery queue), a private redis-server,
and a real `celery worker` process started with no database URL and no secret key: it
reaches the server only through /internal/v1. No reconciler runs here: a wake-up or a report
that the worker dropped would never be made up for, and the test would wait in vain.

Each outage lasts until the worker has met it: until its log says the request the round is
about was refused (`worker.server_api` logs each refused attempt it will try again), never a
fixed time. The database is then started again, and the worker's retry, after the server's
`Retry-After`, gets through.

The figures of each round (how long a queued submission waited for its claim once the
database was back, how many final reports were delivered after an outage) are printed
(`pytest -s`) and written to `$MANIEVAL_ARTEFACTS/outages.txt` when that is set.
"""

from __future__ import annotations

import importlib
import os
import signal
import subprocess
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis as redis_client
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import FINAL_STATES
from manieval.service import Service
from server.kit.settings import Settings
from server.models import State, Submission, Transition, utcnow
from testkit.factories import PASSWORD, embedded_database
from testkit.waiting import poll, until
from testkit.workers import public_api
from tests.private_postgres import PrivatePostgres
from tests.worker.celery_workers import (
    add_challenge,
    celery_server_settings,
    celery_worker,
    wait_ready,
    worker_environment,
)
from tests.worker.redis_server import Redis, free_port

pytestmark = [pytest.mark.sim, pytest.mark.long, pytest.mark.timeout(900)]
ROUNDS = 10
CLAIM_ROUNDS = 3  # each round stops the database at the same point of a claim
MEET_S = 120.0  # how long an outage may wait for the worker to meet it: a bound, not a time
FINAL = {state.value for state in FINAL_STATES}  # as the API spells them
REPO = Path(__file__).resolve().parents[2]
# A run of the scripted policy long enough that an outage can begin after its first episode
# (of 8) and the test see the rest of it run while the database is down.
MID = {"max_episode_steps: 12, episodes: 2": "max_episode_steps: 60, episodes: 4"}


@dataclass
class Stack:
    pg: PrivatePostgres
    settings: Settings
    api: httpx.Client
    sessions: sessionmaker[Session]
    worker: subprocess.Popen[bytes]
    worker_log: Path
    broker: redis_client.Redis
    figures: list[str] = field(default_factory=list)

    def note(self, line: str) -> None:
        print(line, flush=True)
        self.figures.append(line)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    work = tmp_path_factory.mktemp("outages")
    pg = PrivatePostgres()
    redis = Redis(work)
    service: Service | None = None
    worker: subprocess.Popen[bytes] | None = None
    try:
        pg.start()
        redis.start()
        settings = celery_server_settings(
            work,
            database_url=pg.url,
            broker_url=redis.url,
            queue=f"outages-{redis.port}",
            token_rate="1000/minute",
            database_retry_after_s=1,  # each round waits for it once the database is back
        )
        sessions = embedded_database(settings, quota_concurrent=50, quota_per_day=1000)
        add_challenge(settings, "server-mid", **MID)
        service = Service(settings, port=free_port())
        assert service.start(), "the server did not start"
        log = work / "worker.log"
        env = worker_environment(settings, server_url=service.url, data_dir=work / "worker")
        worker = celery_worker(
            env, queues=settings.celery_queue, policies=REPO / "examples" / "policies", log=log
        )
        wait_ready(worker, log)
        api = public_api(service.url)
        r = api.post(
            "/users", json={"username": "alice", "email": "a@example.org", "password": PASSWORD}
        )
        assert r.status_code == 201, r.text
        r = api.post("/auth/token", json={"login": "alice", "password": PASSWORD})
        assert r.status_code == 201, r.text
        api.headers["Authorization"] = f"Bearer {r.json()['token']}"
        broker = redis_client.Redis.from_url(redis.url)
        stack = Stack(pg, settings, api, sessions, worker, log, broker)
        yield stack
        api.close()
        broker.close()
        sessions.kw["bind"].dispose()
        if stack.figures and (artefacts := os.environ.get("MANIEVAL_ARTEFACTS")):
            path = Path(artefacts) / "outages.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("\n".join(stack.figures) + "\n")
    finally:
        if worker is not None and worker.poll() is None:
            os.killpg(worker.pid, signal.SIGKILL)
            worker.wait(30)
        if service is not None:
            service.stop()
        redis.stop()
        pg.remove()


def submit(stack: Stack, challenge: str = "server-tiny") -> int:
    r = stack.api.post("/submissions", json={"challenge": challenge, "image": "local:scripted"})
    assert r.status_code == 202, r.text
    return int(r.json()["id"])


def refused(stack: Stack) -> None:
    """A submit while the database is down: 503, with when to try again."""
    r = stack.api.post("/submissions", json={"challenge": "server-tiny", "image": "local:scripted"})
    assert r.status_code == 503, r.text
    assert int(r.headers["Retry-After"]) > 0
    assert r.json()["error"]["code"] == "unavailable"


def wait_for(
    stack: Stack, sid: int, done: Callable[[dict[str, Any]], bool], timeout: float = 300
) -> dict[str, Any]:
    """Poll until `done(body)`; while the database is down the server may only say 503."""

    def fetch() -> dict[str, Any] | None:
        r = stack.api.get(f"/submissions/{sid}")
        if r.status_code == 200:
            body: dict[str, Any] = r.json()
            return body
        assert r.status_code == 503, r.text
        assert "Retry-After" in r.headers
        return None

    body = poll(fetch, lambda b: b is not None and done(b), f"submission {sid}", timeout=timeout)
    assert body is not None
    return body


def final(stack: Stack, sid: int) -> dict[str, Any]:
    return wait_for(stack, sid, lambda body: body["state"] in FINAL)


@contextmanager
def database_down(stack: Stack) -> Iterator[None]:
    """The database is stopped inside the block; it is started again however the block ends."""
    stack.pg.stop()
    try:
        yield
    finally:
        stack.pg.start()


class Trap:
    """The server stops the database itself inside its next call of `target` once armed, so
    that this one request fails as the database goes (a 503): a point of a request that no
    stop from outside could hit."""

    def __init__(self, stack: Stack, monkeypatch: pytest.MonkeyPatch, target: str) -> None:
        module, name = target.rsplit(".", 1)
        original = getattr(importlib.import_module(module), name)
        self.armed, self.sprung = threading.Event(), threading.Event()
        self.stopped = utcnow()

        def dying(*args: Any, **kwargs: Any) -> Any:
            if self.armed.is_set():
                self.armed.clear()
                self.stopped = utcnow()
                stack.pg.stop()
                self.sprung.set()
            return original(*args, **kwargs)

        monkeypatch.setattr(target, dying)

    def arm(self) -> None:
        self.sprung.clear()
        self.armed.set()

    def wait(self, what: str) -> datetime:
        """Until it stopped the database; returns when."""
        assert self.sprung.wait(MEET_S), f"gave up after {MEET_S:g} s waiting for {what}"
        return self.stopped

    @contextmanager
    def armed_once(self, stack: Stack) -> Iterator[None]:
        """Armed inside the block; the database it stopped is started again however the
        block ends."""
        self.arm()
        try:
            yield
        finally:
            self.armed.clear()
            if self.sprung.is_set():
                stack.pg.start()


def log_size(stack: Stack) -> int:
    return stack.worker_log.stat().st_size


def worker_said(stack: Stack, since: int) -> str:
    """What the worker logged after its log was `since` bytes long."""
    with stack.worker_log.open("rb") as f:
        f.seek(since)
        return f.read().decode(errors="replace")


def worker_says(stack: Stack, since: int, text: str) -> None:
    """Until the worker has logged `text` after its log was `since` bytes long."""

    def said() -> bool:
        assert stack.worker.poll() is None, f"the worker exited:\n{worker_said(stack, since)}"
        return text in worker_said(stack, since)

    until(
        said,
        lambda: f"the worker to log {text!r}; it logged:\n{worker_said(stack, since)[-4000:]}",
        timeout=MEET_S,
        every=0.05,
    )


def refused_by_the_worker(method: str, path: str) -> str:
    """The worker's line for a request of its that met an outage (`worker.server_api`)."""
    return f"server unavailable for {method} /internal/v1{path}"


def spooled(stack: Stack, sid: int) -> Path:
    return stack.worker_log.parent / "worker" / "spool" / f"{sid}-1.json"


def at(value: object) -> datetime:
    return datetime.fromisoformat(str(value))


def history(stack: Stack, sid: int) -> list[State]:
    with stack.sessions() as db:
        return list(
            db.scalars(
                select(Transition.to_state)
                .where(Transition.submission_id == sid)
                .order_by(Transition.id)
            )
        )


def ran_once(stack: Stack, sid: int) -> None:
    """Succeeded in its first attempt, evaluated exactly once."""
    assert history(stack, sid) == [State.QUEUED, State.LAUNCHING, State.RUNNING, State.SUCCEEDED]
    with stack.sessions() as db:
        submission = db.get(Submission, sid)
        assert submission is not None
        assert submission.attempt == 1


def idle(stack: Stack) -> None:
    """Until the worker has taken every wake-up in the broker and acknowledged it."""
    queue = stack.settings.celery_queue
    until(
        lambda: not (stack.broker.llen(queue) or stack.broker.hlen("unacked")),
        "the worker to take and acknowledge every wake-up in the broker",
        timeout=120,
        every=0.1,
    )


def spool_empty(stack: Stack) -> None:
    assert not list(stack.worker_log.parent.glob("worker/spool/*.json"))


def test_the_database_stops_during_runs_and_their_final_reports(
    stack: Stack, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each run ends and its final report reaches the server as the database stops (inside
    the report's request: an outage begun from outside while the run runs is met by the
    trajectory uploads that come before the report, and the report itself would be sent only
    once it is over). The worker is refused, keeps the report in its spool, and delivers it
    once the database is back: the run succeeded, once."""
    trap = Trap(stack, monkeypatch, "server.submissions.internal.report_final")
    for n in range(1, ROUNDS + 1):
        since = log_size(stack)
        with trap.armed_once(stack):
            sid = submit(stack)
            stopped = trap.wait(f"the final report of submission {sid}")
            refused(stack)
            worker_says(
                stack, since, refused_by_the_worker("POST", f"/submissions/{sid}/attempts/1/final")
            )
            assert spooled(stack, sid).is_file(), "the refused final report is not in the spool"
            refused(stack)
        back = utcnow()
        body = final(stack, sid)
        assert body["state"] == "succeeded", body
        ran_once(stack, sid)
        assert at(body["finished_at"]) > stopped  # what ended it was the report sent again
        assert not spooled(stack, sid).exists()
        stack.note(
            f"final report round {n:2}: refused, kept in the spool through "
            f"{(back - stopped).total_seconds():.1f} s of outage, delivered "
            f"{(at(body['finished_at']) - back).total_seconds():+.1f} s after it was back"
        )
    stack.note(f"final reports kept through an outage and delivered after it: {ROUNDS}")
    spool_empty(stack)


def test_the_database_stops_in_the_middle_of_longer_runs(stack: Stack) -> None:
    after = 0
    for n in range(1, ROUNDS + 1):
        sid = submit(stack, "server-mid")
        body = wait_for(
            stack, sid, lambda b: b["state"] in FINAL or bool((b["progress"] or {}).get("done"))
        )
        assert body["state"] == "running", f"the run ended before its outage: {body}"
        progress = body["progress"]
        since, stopped = log_size(stack), utcnow()
        with database_down(stack):
            refused(stack)
            # The evaluation goes on to its end while the database is down: the first of its
            # trajectory uploads, which follow its last episode, is refused.
            worker_says(
                stack,
                since,
                refused_by_the_worker("PUT", f"/submissions/{sid}/attempts/1/trajectories/"),
            )
            refused(stack)
        back = utcnow()
        said = worker_said(stack, since)
        assert f"progress of submission {sid} not delivered" in said  # its heartbeats met it
        body = final(stack, sid)
        assert body["state"] == "succeeded", body
        ran_once(stack, sid)
        after += at(body["finished_at"]) >= stopped
        stack.note(
            f"mid-run round {n:2}: database down {(back - stopped).total_seconds():.1f} s from "
            f"{progress['done']} of {progress['total']} episodes to the run's end; the run "
            f"ended {(at(body['finished_at']) - back).total_seconds():+.1f} s after it was back"
        )
    stack.note(f"longer runs ending after their outage: {after} of {ROUNDS}")
    spool_empty(stack)


def test_a_wake_up_delivered_during_an_outage_is_not_lost(stack: Stack) -> None:
    queue = stack.settings.celery_queue
    delays: list[float] = []
    for n in range(1, ROUNDS + 1):
        idle(stack)  # no stray wake-up of an earlier round may stand in for this one
        since = log_size(stack)
        os.killpg(stack.worker.pid, signal.SIGSTOP)  # the wake-up waits in the broker
        try:
            sid = submit(stack)
            stack.pg.stop()
        finally:
            os.killpg(stack.worker.pid, signal.SIGCONT)
        try:
            # the worker takes the wake-up (holding it until its task ends): it cannot claim
            until(
                lambda: not stack.broker.llen(queue) and stack.broker.hlen("unacked"),
                "the worker to take its wake-up",
                timeout=60,
            )
            refused(stack)
            worker_says(stack, since, refused_by_the_worker("POST", "/claims"))
        finally:
            stack.pg.start()
        back = utcnow()
        body = wait_for(stack, sid, lambda b: b["state"] != "queued", timeout=120)
        claimed = next(t["at"] for t in body["transitions"] if t["to_state"] == "launching")
        delays.append((at(claimed) - back).total_seconds())
        stack.note(f"wake-up round {n:2}: claimed {delays[-1]:.1f} s after the database was back")
        assert final(stack, sid)["state"] == "succeeded"
        ran_once(stack, sid)
    stack.note(
        "wake-up to claim after the database came back: "
        + ", ".join(f"{d:.1f}" for d in sorted(delays))
        + " s"
    )


def test_the_database_stops_between_a_claim_and_its_answer(
    stack: Stack, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server has moved the submission to `launching` for the worker and is reading its
    evaluation when the database stops: the claim must not be half made (a submission
    `launching` for a worker that got a 503 would wait for the reconciler's launch timeout;
    none runs here). The worker's retry claims it once the database is back."""
    trap = Trap(stack, monkeypatch, "server.submissions.internal.assignment")
    for n in range(1, CLAIM_ROUNDS + 1):
        idle(stack)
        since = log_size(stack)
        with trap.armed_once(stack):
            sid = submit(stack)
            trap.wait("the worker's claim")
            refused(stack)
            worker_says(stack, since, refused_by_the_worker("POST", "/claims"))
        back = utcnow()
        body = wait_for(stack, sid, lambda b: b["state"] in FINAL, timeout=120)
        assert body["state"] == "succeeded", body
        ran_once(stack, sid)
        claimed = next(t["at"] for t in body["transitions"] if t["to_state"] == "launching")
        stack.note(
            f"mid-claim round {n}: claimed again {(at(claimed) - back).total_seconds():.1f} s "
            "after the database was back"
        )
