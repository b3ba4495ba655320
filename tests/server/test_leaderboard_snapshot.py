"""The leaderboard API cuts every page, size and format from one read of the phase's board per
version: the pages agree with each other, a change shows once the version is confirmed, and a
reader never waits for another's read of a newer version."""

from __future__ import annotations

import gc
import json
import threading
import time
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from server.leaderboard import snapshot
from server.leaderboard.snapshot import Snapshots
from server.models import LeaderboardEntry, Phase, State, Submission
from server.submissions.reports import report_final, report_state
from testkit.factories import make_challenge, make_user, queue_submission, result_doc

BOARD = "/api/v1/challenges/server-tiny/leaderboard"


def _ranked(db: Session, names: list[str]) -> None:
    challenge = make_challenge(db, quota_per_day=50, quota_concurrent=50)
    for n, name in enumerate(names):
        s = queue_submission(db, make_user(db, name), challenge)
        s.public = True
        db.commit()
        assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
        assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
        successes = [i < len(names) - n for i in range(len(names))]
        assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=result_doc(successes))
        db.commit()


def test_every_page_size_and_format_agrees_with_one_whole_page(
    client: TestClient, db: Session
) -> None:
    names = [f"user{i}" for i in range(7)]
    _ranked(db, names)
    whole = client.get(BOARD, params={"per_page": 10}).json()
    assert [r["username"] for r in whole["items"]] == names
    for per_page in (1, 2, 3):
        cut = []
        for page in range(1, 8 // per_page + 2):
            body = client.get(BOARD, params={"per_page": per_page, "page": page}).json()
            assert (body["total"], body["page"], body["per_page"]) == (7, page, per_page)
            cut += body["items"]
        assert cut == whole["items"]
    csv = client.get(BOARD, params={"per_page": 3, "page": 3, "format": "csv"}).text
    assert [line.split(",")[1] for line in csv.splitlines()[1:]] == ["user6"]
    assert client.get(BOARD, params={"page": 9}).json()["items"] == []


def test_a_change_shows_once_its_version_is_confirmed(
    sessions: sessionmaker[Session], db: Session
) -> None:
    _ranked(db, ["ada", "bob"])
    boards = Snapshots(max_age=3600)
    first = boards.current(sessions, slug="server-tiny", phase="dev")
    assert boards.fresh("server-tiny", "dev") is first  # trusted without a query
    db.execute(update(Phase).values(leaderboard_version=Phase.leaderboard_version + 1))
    db.commit()
    assert boards.fresh("server-tiny", "dev") is first  # within max_age: may lag
    again = boards.current(sessions, slug="server-tiny", phase="dev")
    assert again is not first
    assert again.version == first.version + 1
    assert boards.current(sessions, slug="server-tiny", phase="dev") is again  # confirmed


@pytest.mark.parametrize(("least", "exempted"), [(2, True), (3, False)])
def test_a_whole_read_exempts_a_board_of_enough_rows_from_the_cyclic_collector(
    sessions: sessionmaker[Session],
    db: Session,
    monkeypatch: pytest.MonkeyPatch,
    least: int,
    exempted: bool,
) -> None:
    monkeypatch.setattr(snapshot, "EXEMPT_MIN_ROWS", least)
    _ranked(db, ["ada", "bob"])
    gc.unfreeze()
    board = Snapshots(max_age=3600).current(sessions, slug="server-tiny", phase="dev")
    # the board, and what lived when it was read; a smaller board is not worth a collection
    assert (gc.get_freeze_count() > 0) is exempted
    assert [s.username for s in board.rows] == ["ada", "bob"]


def test_while_one_reader_reads_a_new_version_the_others_serve_the_last_one(
    sessions: sessionmaker[Session], db: Session
) -> None:
    _ranked(db, ["ada"])
    boards = Snapshots(max_age=0.0)
    held = boards.current(sessions, slug="server-tiny", phase="dev")
    db.execute(update(Phase).values(leaderboard_version=Phase.leaderboard_version + 1))
    db.commit()
    boards._reading.add(("server-tiny", "dev", None))  # another thread is reading it now
    assert boards.current(sessions, slug="server-tiny", phase="dev") is held
    boards._reading.clear()
    assert boards.current(sessions, slug="server-tiny", phase="dev").version == held.version + 1


def test_while_one_reader_looks_at_the_database_the_others_take_the_snapshot_as_fresh(
    sessions: sessionmaker[Session], db: Session
) -> None:
    _ranked(db, ["ada"])
    boards = Snapshots(max_age=0.0)
    held = boards.current(sessions, slug="server-tiny", phase="dev")
    assert boards.fresh("server-tiny", "dev") is None  # past max_age: to be confirmed
    boards._reading.add(("server-tiny", "dev", None))  # another thread confirms it now
    assert boards.fresh("server-tiny", "dev") is held  # no thread, no query meanwhile
    boards._reading.clear()
    assert boards.fresh("server-tiny", "dev") is None


def test_a_phases_first_read_is_one_read_however_many_ask_at_once(
    sessions: sessionmaker[Session], db: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    _ranked(db, ["ada", "bob"])
    boards = Snapshots(max_age=3600)
    askers = 6
    reads: list[int] = []
    whole = snapshot.read_whole

    def read_while_the_others_wait(*args: Any, **kwargs: Any) -> snapshot.Snapshot:
        reads.append(1)
        deadline = time.monotonic() + 30  # bounded by progress: the others reach their wait
        while len(boards._read._waiters) < askers - 1 and time.monotonic() < deadline:  # type: ignore[attr-defined]
            time.sleep(0.01)
        return whole(*args, **kwargs)

    monkeypatch.setattr(snapshot, "read_whole", read_while_the_others_wait)
    got: list[snapshot.Snapshot] = []

    def ask() -> None:
        got.append(boards.current(sessions, slug="server-tiny", phase="dev"))

    threads = [threading.Thread(target=ask) for _ in range(askers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(reads) == 1
    assert len(got) == askers
    assert all(board is got[0] for board in got)


def test_every_page_numbers_its_rows_around_baselines_as_the_whole_board(
    sessions: sessionmaker[Session], db: Session
) -> None:
    challenge = make_challenge(db)
    phase = challenge.phases[0]
    start = datetime(2026, 1, 1, tzinfo=UTC)
    scores = [0.9, 0.5, 0.5, 0.95, 0.1, 0.5, 0.7]  # user2 and user5 are baselines
    for i, score in enumerate(scores):
        user = make_user(db, f"user{i}")
        s = Submission(
            user_id=user.id,
            challenge_id=challenge.id,
            phase_id=phase.id,
            image="x",
            pinned_image="x",
            state=State.SUCCEEDED,
            score=score,
            created_at=start + timedelta(minutes=i),
            updated_at=start,
        )
        db.add(s)
        db.flush()
        db.add(
            LeaderboardEntry(
                phase_id=phase.id,
                submission_id=s.id,
                user_id=user.id,
                owner_key=None if i in (2, 5) else user.id,
                baseline=i in (2, 5),
                score=score,
                submitted_at=s.created_at,
                username=user.username,
                summary={},
            )
        )
    db.commit()
    expected = [
        ("user3", 1),
        ("user0", 2),
        ("user6", 3),
        ("user1", 4),
        ("user2", None),
        ("user5", None),
        ("user4", 5),
    ]
    board = Snapshots(max_age=3600).current(sessions, slug="server-tiny", phase="dev")
    for per_page in (1, 2, 3, 7, 10):
        seen = []
        for page in range(1, 8):
            body = json.loads(board.body(page, per_page, "json"))
            assert body["total"] == 7
            seen += [(r["username"], r["rank"]) for r in body["items"]]
        assert seen == expected, per_page
