"""What operators watch: Prometheus metrics, liveness and readiness, and logs a machine can read.

The service's own numbers (queue depth, evaluations running, how long they take, how they end)
come from the database when Prometheus scrapes, not from counters in one process: workers are
Celery processes without an HTTP port, and every API replica then reports the same truth. The
queries are cheap (indexed by state, bounded to the last day) and cached for a few seconds.
HTTP metrics are per process, labelled by route template (never by raw path: bounded labels).
"""

from __future__ import annotations

import hmac
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import timedelta

from fastapi import FastAPI
from fastapi.responses import JSONResponse
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select, text
from sqlalchemy.orm import Session, sessionmaker
from starlette.requests import Request
from starlette.responses import Response

from server.kit.errors import Unauthorized
from server.kit.settings import Settings
from server.models import State, Submission, utcnow

log = logging.getLogger(__name__)

WINDOW = timedelta(hours=24)
CACHE_S = 10.0
QUANTILES = (0.5, 0.9, 0.99)
ERROR_KINDS = (  # our errors, by how their reason starts (worker/, server/)
    ("the worker evaluating it stopped responding", "worker_lost"),
    ("cannot run", "configuration"),
    ("the evaluation could not start", "image_pull"),
    ("cannot create the evaluation job", "kubernetes"),
    ("the kubernetes api", "kubernetes"),
    ("the evaluator failed", "evaluator"),
    ("the evaluation's result could not be read", "evaluator"),
    ("the evaluation's job", "kubernetes"),
)


def error_kind(reason: str) -> str:
    """A bounded label for an `error` reason (the reason itself is free text)."""
    lowered = reason.lower()
    return next((kind for prefix, kind in ERROR_KINDS if lowered.startswith(prefix)), "other")


class ServiceCollector(Collector):
    """Queue depth, evaluations by state, outcomes and durations over the last day."""

    def __init__(self, sessions: sessionmaker[Session], *, cache_s: float = CACHE_S) -> None:
        self._sessions = sessions
        self._cache_s = cache_s
        self._lock = threading.Lock()
        self._cached: tuple[float, list[GaugeMetricFamily]] | None = None

    def collect(self) -> Iterable[GaugeMetricFamily]:
        with self._lock:
            now = time.monotonic()
            if self._cached is None or now - self._cached[0] >= self._cache_s:
                self._cached = (now, list(self._measure()))
            return list(self._cached[1])

    def _measure(self) -> Iterator[GaugeMetricFamily]:
        now = utcnow()
        since = now - WINDOW
        with self._sessions() as db:
            by_state = dict(
                db.execute(select(Submission.state, func.count()).group_by(Submission.state)).all()
            )
            oldest = db.scalar(
                select(func.min(Submission.created_at)).where(Submission.state == State.QUEUED)
            )
            ended = db.execute(
                select(
                    Submission.state,
                    Submission.reason,
                    Submission.result["abort"]["kind"].as_string(),
                    Submission.created_at,
                    Submission.started_at,
                    Submission.finished_at,
                ).where(Submission.finished_at >= since)
            ).all()
        submissions = GaugeMetricFamily(
            "manieval_submissions", "Submissions by state, now.", labels=["state"]
        )
        for state in State:
            submissions.add_metric([state.value], by_state.get(state, 0))
        yield submissions
        yield GaugeMetricFamily(
            "manieval_queue_depth",
            "Submissions waiting for a worker.",
            by_state.get(State.QUEUED, 0),
        )
        running = by_state.get(State.RUNNING, 0) + by_state.get(State.LAUNCHING, 0)
        yield GaugeMetricFamily(
            "manieval_evaluations_running", "Attempts launching or running.", running
        )
        age = (now - oldest).total_seconds() if oldest is not None else 0.0
        yield GaugeMetricFamily(
            "manieval_queue_oldest_seconds", "Age of the oldest queued submission.", max(age, 0.0)
        )
        outcomes = GaugeMetricFamily(
            "manieval_outcomes_24h",
            "Submissions that ended in the last 24 hours, by final state and kind of reason.",
            labels=["state", "kind"],
        )
        counts: dict[tuple[str, str], int] = {}
        runs: list[float] = []
        waits: list[float] = []
        for state, reason, abort_kind, created, started, finished in ended:
            kind = abort_kind or (error_kind(reason) if state == State.ERROR else "")
            counts[(state.value, kind)] = counts.get((state.value, kind), 0) + 1
            if started is not None and finished is not None:
                runs.append((finished - started).total_seconds())
                waits.append((started - created).total_seconds())
        for (state_value, kind), count in sorted(counts.items()):
            outcomes.add_metric([state_value, kind], count)
        yield outcomes
        yield _quantiles(
            "manieval_evaluation_seconds_24h",
            "Evaluation wall time (started to ended) over the last 24 hours.",
            runs,
        )
        yield _quantiles(
            "manieval_queue_wait_seconds_24h",
            "Time from submission to the start of its evaluation, over the last 24 hours.",
            waits,
        )


def _quantiles(name: str, documentation: str, values: list[float]) -> GaugeMetricFamily:
    family = GaugeMetricFamily(name, documentation, labels=["quantile"])
    ordered = sorted(values)
    for q in QUANTILES:
        value = ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else 0.0
        family.add_metric([str(q)], value)
    return family


class HttpMetrics:
    """Requests and their latency by method, route template and status class."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.requests = Counter(
            "manieval_http_requests",
            "HTTP requests handled by this process.",
            ["method", "route", "status"],
            registry=registry,
        )
        self.latency = Histogram(
            "manieval_http_request_seconds",
            "HTTP request latency in this process, by route template.",
            ["route"],
            registry=registry,
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0),
        )

    async def __call__(
        self, request: Request, call_next: Callable[[Request], Awaitable[Response]]
    ) -> Response:
        started = time.perf_counter()
        status = 500
        try:
            response = await call_next(request)
            status = response.status_code
            return response
        finally:
            route = request.scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.requests.labels(request.method, template, f"{status // 100}xx").inc()
            self.latency.labels(template).observe(time.perf_counter() - started)


@dataclass(frozen=True)
class Monitoring:
    """What the monitoring routes of one app read (`app.state.monitoring`)."""

    sessions: sessionmaker[Session]
    settings: Settings
    registry: CollectorRegistry


def install_monitoring(app: FastAPI, sessions: sessionmaker[Session], settings: Settings) -> None:
    """Liveness, readiness and Prometheus metrics (docs/server.md, Monitoring)."""
    registry = CollectorRegistry()
    registry.register(ServiceCollector(sessions))
    app.middleware("http")(HttpMetrics(registry))
    app.state.monitoring = Monitoring(sessions, settings, registry)
    # Module functions reading their app's `Monitoring`, not closures over it: FastAPI caches
    # facts about each endpoint callable process-wide (strong references), and a closure per
    # app kept every app ever made alive (the test suite makes hundreds in one process).
    for path, endpoint in (("/healthz", healthz), ("/readyz", readyz), ("/metrics", metrics)):
        app.add_api_route(path, endpoint, methods=["GET"], include_in_schema=False)


def _monitoring(request: Request) -> Monitoring:
    monitoring: Monitoring = request.app.state.monitoring
    return monitoring


def healthz() -> dict[str, str]:
    return {"status": "ok"}


def readyz(request: Request) -> JSONResponse:
    monitoring = _monitoring(request)
    try:
        with monitoring.sessions() as db:
            db.execute(text("SELECT 1"))
    except Exception:  # the detail may name hosts and users: the log has it, not the answer
        log.exception("readiness: the database does not answer")
        return JSONResponse({"status": "unavailable", "database": "unreachable"}, 503)
    if (problem := broker_problem(monitoring.settings)) is not None:
        log.warning("readiness: the broker does not answer: %s", problem)
        return JSONResponse({"status": "unavailable", "broker": "unreachable"}, 503)
    return JSONResponse({"status": "ok"})


def metrics(request: Request) -> Response:
    monitoring = _monitoring(request)
    token = monitoring.settings.metrics_token
    if token is not None:
        sent = request.headers.get("authorization", "").encode("utf-8", "surrogateescape")
        expected = f"Bearer {token.get_secret_value()}".encode()
        if not hmac.compare_digest(sent, expected):
            raise Unauthorized("send the metrics token: Authorization: Bearer <token>")
    return Response(generate_latest(monitoring.registry), media_type=CONTENT_TYPE_LATEST)


def broker_problem(settings: Settings) -> str | None:
    """Why the Celery broker does not answer, or None (also when there is no broker)."""
    if settings.queue != "celery":
        return None
    import redis

    try:
        with redis.Redis.from_url(
            settings.broker_url, socket_connect_timeout=2, socket_timeout=2
        ) as broker:
            broker.ping()
    except Exception as exc:
        return str(exc) or type(exc).__name__
    return None
