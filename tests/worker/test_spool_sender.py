"""The spool tried again while the worker runs: what a pass sends, skips and sets aside.

A scripted transport stands for the server, as in test_server_api.py; the real worker behind
a cut network link is tests/worker/test_partition.py.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx

from testkit.waiting import until
from tests.worker.test_server_api import REPORT, Answer, client, final_ok, refused
from worker.server_api import Spool
from worker.spool_sender import SpoolSender, resend_pass


def kept(tmp_path: Path, *reports: tuple[int, int], age_s: float = 60.0) -> Spool:
    """A spool holding REPORT for each (submission, attempt), written `age_s` ago."""
    spool = Spool(tmp_path / "spool")
    for sid, attempt in reports:
        spool.put(sid, attempt, REPORT)
        written = time.time() - age_s
        os.utime(spool.directory / f"{sid}-{attempt}.json", (written, written))
    return spool


def paths(seen: list[httpx.Request]) -> list[str]:
    return [r.url.path.removeprefix("/internal/v1/submissions/") for r in seen]


def test_a_pass_stops_at_the_first_report_that_cannot_be_delivered(tmp_path: Path) -> None:
    kept(tmp_path, (1, 1), (2, 1))
    seen: list[httpx.Request] = []
    api = client(tmp_path, [refused()], seen, report_patience_s=5)
    assert resend_pass(api) == 0
    assert paths(seen) == ["1/attempts/1/final"]  # tried once, no backoff: the next pass retries
    assert len(list(api.spool)) == 2


def test_a_report_still_retried_by_its_writer_is_left_to_it(tmp_path: Path) -> None:
    kept(tmp_path, (1, 1))
    kept(tmp_path, (2, 1), age_s=0.0)
    seen: list[httpx.Request] = []
    api = client(tmp_path, [final_ok()], seen, report_patience_s=30)
    assert resend_pass(api) == 1
    assert paths(seen) == ["1/attempts/1/final"]
    assert [k.submission_id for k in api.spool] == [2]


def test_a_report_about_a_replaced_attempt_is_dropped(tmp_path: Path) -> None:
    kept(tmp_path, (1, 1))
    api = client(tmp_path, [httpx.Response(409, json={"error": {}})], [], report_patience_s=5)
    assert resend_pass(api) == 1
    assert list(api.spool) == []


def test_a_report_refused_for_good_is_set_aside_and_the_others_go_on(tmp_path: Path) -> None:
    kept(tmp_path, (1, 1), (2, 1))
    seen: list[httpx.Request] = []
    answers: list[Answer] = [httpx.Response(422, json={"error": {}}), final_ok()]
    api = client(tmp_path, answers, seen, report_patience_s=5)
    assert resend_pass(api) == 1
    assert paths(seen) == ["1/attempts/1/final", "2/attempts/1/final"]
    assert list(api.spool) == []
    assert (tmp_path / "spool" / "1-1.bad").exists()


def test_the_sender_delivers_a_kept_report_once_the_server_answers_again(
    tmp_path: Path,
) -> None:
    spool = kept(tmp_path, (3, 1))
    seen: list[httpx.Request] = []
    answers: list[Answer] = [refused(), refused(), final_ok()]
    api = client(tmp_path, answers, seen, report_patience_s=5)
    sender = SpoolSender(api, every_s=0.05)
    sender.start()
    try:
        until(lambda: not list(spool), "the sender to deliver the kept report", timeout=30)
    finally:
        sender.stop(timeout=10)
    assert paths(seen) == ["3/attempts/1/final"] * 3
