"""The worker's client of /internal/v1: what it retries, what it keeps, what it gives up on.

The server side is a scripted transport here (answers in the order a test lists them); the
real server behind the same client is exercised by the Celery, embedded and fault tests.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from internal_api.schemas import FinalReport, State
from worker.server_api import ServerAPI, ServerUnavailable, Spool, WorkerRefused

Answer = httpx.Response | Exception


def scripted(answers: list[Answer], seen: list[httpx.Request]) -> httpx.MockTransport:
    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        answer = answers.pop(0) if len(answers) > 1 else answers[0]
        if isinstance(answer, Exception):
            raise answer
        return answer

    return httpx.MockTransport(handle)


def client(
    tmp_path: Path, answers: list[Answer], seen: list[httpx.Request], **patience: float
) -> ServerAPI:
    http = httpx.Client(
        base_url="http://server.test/internal/v1", transport=scripted(answers, seen)
    )
    return ServerAPI(http, spool=Spool(tmp_path / "spool"), **patience)


def final_ok() -> httpx.Response:
    return httpx.Response(200, json={"applied": True, "state": "succeeded"})


REPORT = FinalReport(state=State.FAILED, reason="the policy crashed", log_tail="Traceback")
refused: Callable[[], Exception] = lambda: httpx.ConnectError("connection refused")  # noqa: E731


def test_a_final_report_survives_an_outage_and_is_sent_when_the_server_is_back(
    tmp_path: Path,
) -> None:
    seen: list[httpx.Request] = []
    answers: list[Answer] = [
        refused(),
        httpx.Response(503, headers={"Retry-After": "0"}),
        httpx.Response(502),
        final_ok(),
    ]
    api = client(tmp_path, answers, seen, report_patience_s=60)
    assert api.final(4, 2, REPORT) == State.SUCCEEDED
    assert [r.url.path for r in seen] == ["/internal/v1/submissions/4/attempts/2/final"] * 4
    assert json.loads(seen[-1].content)["reason"] == "the policy crashed"
    assert list(api.spool) == []  # accepted: nothing kept


def test_an_undeliverable_final_report_stays_in_the_spool_for_the_next_start(
    tmp_path: Path,
) -> None:
    seen: list[httpx.Request] = []
    api = client(tmp_path, [refused()], seen, report_patience_s=0.5)
    assert api.final(4, 2, REPORT) is None
    kept = list(api.spool)
    assert [(k.submission_id, k.attempt, k.report) for k in kept] == [(4, 2, REPORT)]

    restarted = client(tmp_path, [final_ok()], seen)  # a new process, the same spool
    assert restarted.flush_spool() == 1
    assert list(restarted.spool) == []


def test_a_report_about_a_replaced_attempt_is_dropped_not_retried(tmp_path: Path) -> None:
    seen: list[httpx.Request] = []
    api = client(tmp_path, [httpx.Response(409, json={"error": {}})], seen)
    assert api.final(4, 1, REPORT) is None
    assert len(seen) == 1
    assert list(api.spool) == []


def test_a_claim_waits_out_a_database_outage(tmp_path: Path) -> None:
    seen: list[httpx.Request] = []
    answers: list[Answer] = [
        httpx.Response(503, headers={"Retry-After": "0"}),
        httpx.Response(503),
        httpx.Response(204),
    ]
    api = client(tmp_path, answers, seen, claim_patience_s=60)
    assert api.claim("w1") is None
    assert len(seen) == 3
    assert json.loads(seen[0].content) == {"worker": "w1"}


def test_each_refused_attempt_that_will_be_retried_is_logged_with_its_wait(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    answers: list[Answer] = [
        httpx.Response(503, headers={"Retry-After": "0"}, text="database down"),
        refused(),
        httpx.Response(204),
    ]
    api = client(tmp_path, answers, [], claim_patience_s=60)
    once = client(tmp_path, [httpx.Response(503)], [])
    with caplog.at_level(logging.WARNING, logger="worker.server_api"):
        assert api.claim("w1") is None
        with pytest.raises(ServerUnavailable):
            once.progress(4, 1, {"done": 3})  # tried once: not retried, no line
    lines = [r.getMessage() for r in caplog.records if r.name == "worker.server_api"]
    assert len(lines) == 2, lines
    assert lines[0].startswith("server unavailable for POST /internal/v1/claims: HTTP 503")
    assert "ConnectError" in lines[1]
    assert all(re.search(r"; trying again in \d+\.\d s$", line) for line in lines), lines


def test_a_claim_gives_up_after_its_patience(tmp_path: Path) -> None:
    api = client(tmp_path, [refused()], [], claim_patience_s=0.3)
    with pytest.raises(ServerUnavailable, match="ConnectError"):
        api.claim("w1")


def test_progress_is_tried_once(tmp_path: Path) -> None:
    seen: list[httpx.Request] = []
    api = client(tmp_path, [httpx.Response(503)], seen)
    with pytest.raises(ServerUnavailable):
        api.progress(4, 1, {"done": 3})
    assert len(seen) == 1


def test_a_refused_worker_token_is_a_configuration_error(tmp_path: Path) -> None:
    api = client(tmp_path, [httpx.Response(401, json={})], [])
    with pytest.raises(WorkerRefused, match="worker token"):
        api.claim("w1")


def test_a_stopping_worker_does_not_sit_out_the_backoff(tmp_path: Path) -> None:
    stop = threading.Event()
    seen: list[httpx.Request] = []
    api = client(tmp_path, [refused()], seen, report_patience_s=3600)
    api.stop = stop
    timer = threading.Timer(0.5, stop.set)
    timer.start()
    assert api.final(4, 2, REPORT) is None  # returned although the patience is an hour
    timer.join()
    assert len(list(api.spool)) == 1


def test_an_unreadable_spool_file_is_set_aside(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool")
    spool.put(1, 1, REPORT)
    (tmp_path / "spool" / "2-1.json").write_text("{not json")
    assert [k.submission_id for k in spool] == [1]
    assert (tmp_path / "spool" / "2-1.bad").exists()


def test_a_final_report_with_its_result_document_is_spooled_and_sent_whole(
    tmp_path: Path,
) -> None:
    from testkit.factories import result_doc

    report = FinalReport(state=State.SUCCEEDED, reason="score 0.500", result=result_doc([True]))
    seen: list[httpx.Request] = []
    api = client(tmp_path, [refused()], seen, report_patience_s=0.3)
    assert api.final(5, 1, report) is None
    assert [k.report for k in api.spool] == [report]  # datetimes and all, through JSON
    restarted = client(tmp_path, [final_ok()], seen)
    assert restarted.flush_spool() == 1
    assert json.loads(seen[-1].content)["result"]["score"] == report.result.score  # type: ignore[union-attr]
