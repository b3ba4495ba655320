"""Metrics from the database, bounded labels, and JSON log lines."""

from __future__ import annotations

import json
import logging
from datetime import timedelta

import pytest
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy.orm import Session, sessionmaker

from internal_api.logs import JsonFormatter, configure_logging
from server.kit.observability import ServiceCollector, error_kind
from server.models import State, Submission, utcnow
from server.submissions.reports import report_final, report_state
from testkit.factories import make_challenge, make_user, queue_submission


def samples(collector: ServiceCollector) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    registry = CollectorRegistry()
    registry.register(collector)
    text = generate_latest(registry).decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def _queue(db: Session, n: int) -> list[Submission]:
    challenge = make_challenge(db, quota_concurrent=100, quota_per_day=100)
    user = make_user(db, "alice")
    queued = [queue_submission(db, user, challenge) for _ in range(n)]
    db.commit()
    return queued


def test_queue_depth_running_and_states_come_from_the_database(
    sessions: sessionmaker[Session], db: Session
) -> None:
    a, *_ = _queue(db, 3)
    assert report_state(db, a.id, 1, State.LAUNCHING, "go")
    assert report_state(db, a.id, 1, State.RUNNING, "go")
    db.commit()
    got = samples(ServiceCollector(sessions, cache_s=0))
    assert got[("manieval_queue_depth", ())] == 2
    assert got[("manieval_evaluations_running", ())] == 1
    assert got[("manieval_submissions", (("state", "queued"),))] == 2
    assert got[("manieval_submissions", (("state", "succeeded"),))] == 0
    assert got[("manieval_queue_oldest_seconds", ())] >= 0


def test_outcomes_and_durations_of_the_last_day(
    sessions: sessionmaker[Session], db: Session
) -> None:
    a, b, c = _queue(db, 3)
    for s in (a, b, c):
        assert report_state(db, s.id, 1, State.LAUNCHING, "go")
        assert report_state(db, s.id, 1, State.RUNNING, "go")
    assert report_final(db, a.id, 1, State.ERROR, "the worker evaluating it stopped responding")
    assert report_final(db, b.id, 1, State.ERROR, "cannot run: no engine")
    assert report_final(db, c.id, 1, State.CANCELLED, "cancelled by its owner")
    c.started_at = c.finished_at - timedelta(seconds=90)  # type: ignore[operator]
    db.commit()
    got = samples(ServiceCollector(sessions, cache_s=0))
    assert got[("manieval_outcomes_24h", (("kind", "worker_lost"), ("state", "error")))] == 1
    assert got[("manieval_outcomes_24h", (("kind", "configuration"), ("state", "error")))] == 1
    assert got[("manieval_outcomes_24h", (("kind", ""), ("state", "cancelled")))] == 1
    assert got[("manieval_evaluation_seconds_24h", (("quantile", "0.99"),))] == pytest.approx(
        90, abs=1
    )


def test_results_are_cached_between_scrapes(sessions: sessionmaker[Session], db: Session) -> None:
    collector = ServiceCollector(sessions, cache_s=3600)
    assert samples(collector)[("manieval_queue_depth", ())] == 0
    _queue(db, 1)
    assert samples(collector)[("manieval_queue_depth", ())] == 0  # still the cached figure


@pytest.mark.parametrize(
    ("reason", "kind"),
    [
        ("the worker evaluating it stopped responding; queued again", "worker_lost"),
        ("cannot run: no container engine is configured", "configuration"),
        ("the evaluation could not start: the policy container: ImagePullBackOff", "image_pull"),
        ("the evaluator failed: RuntimeError: x", "evaluator"),
        ("anything <script> else", "other"),
    ],
)
def test_error_reasons_map_to_a_few_kinds(reason: str, kind: str) -> None:
    assert error_kind(reason) == kind


def test_json_log_lines_carry_level_logger_message_and_exception() -> None:
    record = logging.LogRecord("manieval.x", logging.ERROR, __file__, 1, "ended %s", ("ok",), None)
    record.submission_id = 7
    try:
        raise ValueError("boom")
    except ValueError:
        import sys

        record.exc_info = sys.exc_info()
    line = json.loads(JsonFormatter().format(record))
    assert line["level"] == "error"
    assert (line["logger"], line["message"], line["submission_id"]) == ("manieval.x", "ended ok", 7)
    assert "ValueError: boom" in line["exception"]
    assert line["time"].endswith("Z")


def test_configure_logging_routes_uvicorn_through_one_json_handler(
    capsys: pytest.CaptureFixture[str],
) -> None:
    root = logging.getLogger()
    saved = (root.handlers[:], root.level)
    try:
        configure_logging("json")
        logging.getLogger("uvicorn.access").info('127.0.0.1 - "GET / HTTP/1.1" 200')
        line = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
        assert line["logger"] == "uvicorn.access"
    finally:
        root.handlers[:], _ = saved
        root.setLevel(saved[1])


def test_the_window_is_a_day(sessions: sessionmaker[Session], db: Session) -> None:
    (a,) = _queue(db, 1)
    assert report_state(db, a.id, 1, State.LAUNCHING, "go")
    assert report_final(db, a.id, 1, State.ERROR, "cannot run: x")
    a.finished_at = utcnow() - timedelta(days=2)
    db.commit()
    got = samples(ServiceCollector(sessions, cache_s=0))
    assert not any(name == "manieval_outcomes_24h" for name, _ in got)
