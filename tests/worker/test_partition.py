"""Workers on other hosts, over a network link that is cut mid-evaluation and healed.

Two real `celery worker` processes, each in a network namespace of its own, reach the server
and the broker only across a veth pair to a bridge (tests/worker/netns.py). The server (in
this process, so the test reads its database and drives its settings), its Postgres (on
loopback: only the server talks to it) and its Redis stay in this namespace, the server and
Redis listening on the bridge's address alone. That is the shape of a real deployment: the
workers on other hosts, the database behind the server. A cut sets the bridge's end of one
worker's veth pair down: a pulled cable, whose packets vanish without an answer, so the
worker meets timeouts, as in a real partition, and not the refusals of a server that is down
(tests/worker/test_outages.py). No `tc netem`: the kernels here lack it.

- A cut shorter than the heartbeat timeout but longer than the worker's report patience: the
  evaluation goes on, its final report is kept in the spool, and the worker's spool sender
  delivers it once the link is back; the attempt ends as it ran, once.
- A cut past the heartbeat timeout: the reconciler (its pass asked for by the test, as beat
  would) ends the attempt `error` with the cause `worker_lost` (ours: no quota) and queues it
  once more, the other worker runs it to its end, and the cut-off worker's late final report
  of the replaced attempt is refused (409: `server.submissions.reports._current`) and dropped
  from its spool, the submission unchanged.

The timeouts are the ones a deployment sets, made short: the server's heartbeat timeout, the
workers' report patience, request timeout and spool retry interval.
"""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import FINAL_STATES
from manieval.service import Service
from server.models import Cause, State, Submission, TaskResultRow, Transition, utcnow
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
from tests.worker.netns import Host, Network, make_network
from tests.worker.redis_server import Redis, free_port
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

pytestmark = [pytest.mark.sim, pytest.mark.long, pytest.mark.timeout(600)]
REPO = Path(__file__).resolve().parents[2]
FINAL = {state.value for state in FINAL_STATES}
HEARTBEAT_TIMEOUT_S = 8.0  # the server's; no reconciler runs but the test's passes
WORKER = {
    "MANIEVAL_REPORT_PATIENCE_S": "2",  # the retry window a cut outlasts
    "MANIEVAL_REQUEST_TIMEOUT_S": "3",
    "MANIEVAL_SPOOL_RETRY_S": "0.5",
    "NO_PROXY": "*",  # the server is on the test's own network, never behind a proxy
}
# Four episodes of about two seconds: a cut after the first leaves the rest to run meanwhile.
LONGER = {"max_episode_steps: 12, episodes: 2": "max_episode_steps: 60, episodes: 2"}
WAIT_S = 240.0


@dataclass
class Cluster:
    network: Network
    api: httpx.Client
    reconciler: ServerAPI
    sessions: sessionmaker[Session]
    workers: dict[str, Path]
    """Each host's worker log (its data directory beside it)."""

    def host_running(self, sid: int) -> Host:
        with self.sessions() as db:
            submission = db.get(Submission, sid)
            assert submission is not None
            assert submission.worker is not None
            return self.network.hosts[submission.worker.removeprefix("partition-")]

    def said(self, host: Host, line: str) -> bool:
        return line in self.workers[host.name].read_text(errors="replace")

    def spool(self, host: Host) -> list[Path]:
        return list((self.workers[host.name].parent / host.name / "spool").glob("*.json"))


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    work = tmp_path_factory.mktemp("partition")
    network = make_network("a", "b")
    pg: PrivatePostgres | None = None
    redis: Redis | None = None
    service: Service | None = None
    workers: list[subprocess.Popen[bytes]] = []
    try:
        pg = PrivatePostgres()
        redis = Redis(work, host=network.address)
        pg.start()
        redis.start()
        settings = celery_server_settings(
            work,
            database_url=pg.url,
            broker_url=redis.url,
            queue=f"partition-{redis.port}",
            heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S,
        )
        sessions = embedded_database(settings, quota_concurrent=50, quota_per_day=1000)
        add_challenge(settings, "partition", **LONGER)
        service = Service(settings, host=network.address, port=free_port())
        assert service.start(), "the server did not start"
        logs = {}
        for host in network.hosts.values():
            logs[host.name] = work / f"{host.name}.log"
            env = worker_environment(
                settings,
                server_url=service.url,
                data_dir=work / host.name,
                MANIEVAL_WORKER_NAME=f"partition-{host.name}",
                **WORKER,
            )
            workers.append(
                celery_worker(
                    env,
                    queues=settings.celery_queue,
                    policies=REPO / "examples" / "policies",
                    log=logs[host.name],
                    prefix=host.exec,
                )
            )
        for process, log in zip(workers, logs.values(), strict=True):
            wait_ready(process, log)
        reconciler = ServerAPI.connect(
            WorkerSettings(
                server_url=service.url,
                worker_token=settings.secret("worker_token"),  # type: ignore[arg-type]
                data_dir=work / "reconciler",
                request_timeout_s=30,
            )
        )
        api = participant(service.url)
        yield Cluster(network, api, reconciler, sessions, logs)
        api.close()
        reconciler.close()
        sessions.kw["bind"].dispose()
    finally:
        for process in workers:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(30)
        if service is not None:
            service.stop()
        if redis is not None:
            redis.stop()
        if pg is not None:
            pg.remove()
        network.remove()


def participant(url: str) -> httpx.Client:
    api = public_api(url)
    r = api.post(
        "/users", json={"username": "alice", "email": "a@example.org", "password": PASSWORD}
    )
    assert r.status_code == 201, r.text
    r = api.post("/auth/token", json={"login": "alice", "password": PASSWORD})
    assert r.status_code == 201, r.text
    api.headers["Authorization"] = f"Bearer {r.json()['token']}"
    return api


def submit(cluster: Cluster) -> int:
    r = cluster.api.post("/submissions", json={"challenge": "partition", "image": "local:scripted"})
    assert r.status_code == 202, r.text
    return int(r.json()["id"])


def body(cluster: Cluster, sid: int) -> dict[str, Any]:
    r = cluster.api.get(f"/submissions/{sid}")
    assert r.status_code == 200, r.text
    result: dict[str, Any] = r.json()
    return result


def mid_run(cluster: Cluster, sid: int) -> Host:
    """Until the submission's first episode is done (more to run); the worker running it."""
    poll(
        lambda: body(cluster, sid),
        lambda b: b["state"] in FINAL or bool((b["progress"] or {}).get("done")),
        f"submission {sid} to finish an episode",
        timeout=WAIT_S,
    )
    state = body(cluster, sid)
    # the cut must come mid-evaluation, with episodes left to run while it lasts
    assert state["state"] == "running", state
    assert state["progress"]["done"] < state["progress"]["total"], state
    return cluster.host_running(sid)


def kept(cluster: Cluster, host: Host, sid: int, attempt: int) -> None:
    """Until the worker gave up sending the attempt's final report and kept it (its report
    patience outlasted by the cut)."""
    line = f"the final report of submission {sid} attempt {attempt} is kept in"
    until(lambda: cluster.said(host, line), f"the worker on {host.name} to keep {sid}/{attempt}",
          timeout=WAIT_S)  # fmt: skip
    assert cluster.spool(host), "kept, yet not in the spool"


def final(cluster: Cluster, sid: int) -> dict[str, Any]:
    return poll(
        lambda: body(cluster, sid),
        lambda b: b["state"] in FINAL,
        f"submission {sid} to end",
        timeout=WAIT_S,
    )


def history(cluster: Cluster, sid: int) -> list[tuple[State, Cause | None]]:
    with cluster.sessions() as db:
        rows = db.execute(
            select(Transition.to_state, Transition.cause)
            .where(Transition.submission_id == sid)
            .order_by(Transition.id)
        )
        return [(state, cause) for state, cause in rows]


def results_of(cluster: Cluster, sid: int, attempt: int) -> int:
    with cluster.sessions() as db:
        return int(
            db.scalar(
                select(func.count())
                .select_from(TaskResultRow)
                .where(TaskResultRow.submission_id == sid, TaskResultRow.attempt == attempt)
            )
            or 0
        )


def at(value: object) -> datetime:
    return datetime.fromisoformat(str(value))


def test_a_final_report_kept_through_a_cut_is_delivered_when_the_link_returns(
    cluster: Cluster,
) -> None:
    sid = submit(cluster)
    host = mid_run(cluster, sid)
    cluster.network.cut(host)
    try:
        kept(cluster, host, sid, 1)
        assert body(cluster, sid)["state"] == "running"  # the server has heard nothing
    finally:
        healing = utcnow()
        cluster.network.heal(host)
    ended = final(cluster, sid)
    assert ended["state"] == "succeeded", ended
    assert at(ended["finished_at"]) >= healing  # delivered after the link returned
    assert history(cluster, sid) == [
        (State.QUEUED, None),
        (State.LAUNCHING, None),
        (State.RUNNING, None),
        (State.SUCCEEDED, None),
    ]
    until(lambda: not cluster.spool(host), f"the spool on {host.name} to empty", timeout=WAIT_S)


def test_a_worker_cut_off_past_the_heartbeat_timeout_loses_its_attempt_to_the_other(
    cluster: Cluster,
) -> None:
    sid = submit(cluster)
    host = mid_run(cluster, sid)
    other = next(h for h in cluster.network.hosts.values() if h != host)
    cluster.network.cut(host)
    try:

        def replaced() -> bool:  # the reconciler's passes, until it has queued attempt 2
            cluster.reconciler.reconcile()
            return bool(body(cluster, sid)["attempt"] == 2)

        until(replaced, f"the reconciler to replace attempt 1 of {sid}", timeout=WAIT_S, every=1)
        kept(cluster, host, sid, 1)  # the cut-off worker ran attempt 1 to its end meanwhile
        ended = final(cluster, sid)  # attempt 2 on the other worker, the link still cut
        assert cluster.host_running(sid) == other
    finally:
        cluster.network.heal(host)
    until(lambda: not cluster.spool(host), f"the spool on {host.name} to empty", timeout=WAIT_S)
    # The late report of attempt 1 was refused (409) and dropped: the submission is attempt 2's.
    assert ended["state"] == "succeeded", ended
    now = body(cluster, sid)
    seen = ("state", "reason", "score", "finished_at", "transitions", "tasks")
    assert {k: now[k] for k in seen} == {k: ended[k] for k in seen}
    assert history(cluster, sid) == [
        (State.QUEUED, None),
        (State.LAUNCHING, None),
        (State.RUNNING, None),
        (State.ERROR, Cause.WORKER_LOST),  # ours: no quota used, queued once more
        (State.QUEUED, None),
        (State.LAUNCHING, None),
        (State.RUNNING, None),
        (State.SUCCEEDED, None),
    ]
    assert results_of(cluster, sid, 1) == 0
    assert results_of(cluster, sid, 2) > 0
