"""The submission page's event stream: every transition in order, progress, an end event at a
final state after which the stream closes, keep-alives, a bounded lifetime, and resuming."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from server.app import create_app
from server.kit.settings import Settings
from server.models import State, Transition
from server.submissions.events import StreamTiming
from server.submissions.reports import report_final, report_progress, report_state
from testkit.factories import (
    RecordingQueue,
    fake_resolve_for,
    make_challenge,
    make_user,
    queue_submission,
)
from tests.web.helpers import WEB_CONDITIONS, browser, result_doc


@dataclass
class Event:
    name: str  # "comment" for a keep-alive line
    data: dict[str, object]
    id: str | None = None


def events(lines: Iterator[str]) -> Iterator[Event]:
    """Parse a text/event-stream as it arrives."""
    name, data, event_id = "message", "", None
    for line in lines:
        if line.startswith(":"):
            yield Event("comment", {})
        elif line.startswith("event: "):
            name = line[7:]
        elif line.startswith("data: "):
            data = line[6:]
        elif line.startswith("id: "):
            event_id = line[4:]
        elif line == "" and data:
            yield Event(name, json.loads(data), event_id)
            name, data, event_id = "message", "", None


@pytest.fixture
def live(settings: Settings, committed_sessions: sessionmaker[Session]) -> TestClient:
    app = create_app(
        settings,
        sessions=committed_sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(settings),
        background=False,
    )
    # No fallback reads: every change must arrive because it was pushed.
    app.state.event_timing = StreamTiming(fallback_s=3600, keepalive_s=3600, max_s=3600)
    return TestClient(app, follow_redirects=False)


def queued(sessions: sessionmaker[Session], *, public: bool = True) -> int:
    with sessions() as db:
        challenge = make_challenge(db)
        s = queue_submission(db, make_user(db, "alice"), challenge)
        s.public = public
        db.commit()
        return s.id


def step(sessions: sessionmaker[Session], change: str, sid: int) -> None:
    with sessions.begin() as db:
        if change == "launching":
            report_state(db, sid, 1, State.LAUNCHING, "starting the policy")
        elif change == "running":
            report_state(db, sid, 1, State.RUNNING, "evaluating")
        elif change == "progress":
            report_progress(db, sid, 1, {"done": 1, "total": 4, "task": "PickCube-v1"})
        else:
            report_final(
                db,
                sid,
                1,
                State.SUCCEEDED,
                "all episodes ran",
                result=result_doc([True], conditions=WEB_CONDITIONS),
            )


def test_the_stream_follows_each_change_and_closes_at_the_final_state(
    live: TestClient, committed_sessions: sessionmaker[Session]
) -> None:
    sid = queued(committed_sessions)
    page = live.get(f"/submissions/{sid}").text
    url = re.search(r'data-events="([^"]+)"', page)
    assert url
    assert url.group(1).startswith(f"/submissions/{sid}/events?after=")
    seen: list[tuple[str, object]] = []
    with live.stream("GET", url.group(1)) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        assert r.headers["cache-control"] == "no-store"
        stream = events(r.iter_lines())
        # Each change is made only after the previous one arrived: no timing involved.
        for change, expected in [
            ("launching", "transition"),
            ("running", "transition"),
            ("progress", "progress"),
            ("succeeded", "transition"),
        ]:
            step(committed_sessions, change, sid)
            event = next(e for e in stream if e.name != "comment")
            assert event.name == expected
            seen.append((event.name, event.data.get("to", event.data.get("done"))))
        end = next(stream)
        assert end.name == "end"
        assert end.data == {
            "state": "succeeded",
            "reason": "all episodes ran",
        }
        assert list(stream) == []  # the server closed the stream
    assert seen == [
        ("transition", "launching"),
        ("transition", "running"),
        ("progress", 1),
        ("transition", "succeeded"),
    ]


def test_a_reconnecting_browser_gets_what_it_missed_and_an_ended_one_gets_the_end(
    live: TestClient, committed_sessions: sessionmaker[Session]
) -> None:
    sid = queued(committed_sessions)
    for change in ("launching", "running", "succeeded"):
        step(committed_sessions, change, sid)
    with committed_sessions() as db:
        ids = [t.id for t in db.query(Transition).filter_by(submission_id=sid).order_by("id")]
    r = live.get(f"/submissions/{sid}/events", headers={"Last-Event-ID": str(ids[1])})
    got = list(events(iter(r.text.split("\n"))))
    assert [(e.name, e.id) for e in got] == [
        ("transition", str(ids[2])),
        ("transition", str(ids[3])),
        ("end", None),
    ]


def test_an_idle_stream_sends_keep_alives_and_ends_at_its_time_bound(
    live: TestClient, committed_sessions: sessionmaker[Session]
) -> None:
    sid = queued(committed_sessions)
    live.app.state.event_timing = StreamTiming(fallback_s=0.01, keepalive_s=0, max_s=0)  # type: ignore[attr-defined]
    with committed_sessions() as db:
        last = max(t.id for t in db.query(Transition).filter_by(submission_id=sid))
    text = live.get(f"/submissions/{sid}/events?after={last}").text
    assert text.startswith("retry: ")
    assert ": keep-alive" in text
    assert "event: end" not in text  # not ended: the browser reconnects where it was


def test_an_idle_stream_reads_the_database_once_however_many_keep_alives_it_sends(
    live: TestClient, committed_sessions: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    from server.submissions import events as stream

    sid = queued(committed_sessions)
    reads: list[int] = []
    poll = stream._poll
    monkeypatch.setattr(stream, "_poll", lambda *args: reads.append(1) or poll(*args))
    live.app.state.event_timing = StreamTiming(fallback_s=3600, keepalive_s=0.02, max_s=0.5)  # type: ignore[attr-defined]
    text = live.get(f"/submissions/{sid}/events").text
    assert text.count(": keep-alive") >= 2
    assert len(reads) == 1  # nothing changed: no reads after the first


def test_private_streams_are_404_to_others_and_open_to_the_owner(
    live: TestClient, committed_sessions: sessionmaker[Session]
) -> None:
    sid = queued(committed_sessions, public=False)
    with committed_sessions() as db:
        make_user(db, "bob")
    assert live.get(f"/submissions/{sid}/events").status_code == 404
    assert browser(live, "bob").get(f"/submissions/{sid}/events").status_code == 404
    live.app.state.event_timing = StreamTiming(fallback_s=0.01, keepalive_s=0, max_s=0)  # type: ignore[attr-defined]
    owner = browser(live, "alice").get(f"/submissions/{sid}/events")
    assert owner.status_code == 200
    assert "event: transition" in owner.text


def test_open_streams_are_bounded_per_client(
    live: TestClient, committed_sessions: sessionmaker[Session]
) -> None:
    from server.submissions.events import StreamSlots

    sid = queued(committed_sessions)
    slots = StreamSlots(total=10, per_client=1)
    live.app.state.event_slots = slots  # type: ignore[attr-defined]
    assert slots.take("testclient")  # this client already has its one stream open
    r = live.get(f"/submissions/{sid}/events", headers={"Accept": "text/event-stream"})
    assert r.status_code == 503
    assert r.headers["retry-after"] == "10"
    slots.give_back("testclient")
    assert slots.take("someone-else")
    assert slots.take("testclient")


def test_a_view_closes_at_once_when_its_submission_is_made_private(
    live: TestClient, committed_sessions: sessionmaker[Session]
) -> None:
    from server.models import Submission, User
    from server.submissions.service import edit

    sid = queued(committed_sessions, public=True)
    with live.stream("GET", f"/submissions/{sid}/events") as r:  # anonymous: public only
        stream = events(r.iter_lines())
        assert next(e for e in stream if e.name != "comment").name == "transition"
        with committed_sessions.begin() as db:
            submission = db.get(Submission, sid)
            assert submission is not None
            owner = db.get(User, submission.user_id)
            assert owner is not None
            edit(db, user=owner, submission=submission, public=False)
        # Pushed, not read on a timer (the fixture's streams never read unprompted).
        assert next(e for e in stream if e.name != "comment").name == "gone"
