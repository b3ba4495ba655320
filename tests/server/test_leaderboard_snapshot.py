"""The leaderboard API cuts every page, size and format from one read of the phase's board per
version: the pages agree with each other, a change shows once the version is confirmed, and a
reader never waits for another's read of a newer version."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from server.leaderboard.snapshot import Snapshots
from server.models import Phase, State
from server.submissions.reports import report_final, report_state
from tests.factories import make_challenge, make_user, queue_submission, result_doc

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


def test_while_one_reader_reads_a_new_version_the_others_serve_the_last_one(
    sessions: sessionmaker[Session], db: Session
) -> None:
    _ranked(db, ["ada"])
    boards = Snapshots(max_age=0.0)
    held = boards.current(sessions, slug="server-tiny", phase="dev")
    db.execute(update(Phase).values(leaderboard_version=Phase.leaderboard_version + 1))
    db.commit()
    boards._reading.add(("server-tiny", "dev"))  # another thread is reading it now
    assert boards.current(sessions, slug="server-tiny", phase="dev") is held
    boards._reading.clear()
    assert boards.current(sessions, slug="server-tiny", phase="dev").version == held.version + 1
