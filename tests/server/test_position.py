"""A queued submission's place and expected start: the fair claim order and the challenge's
recent evaluation times."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from sqlalchemy.orm import Session

from server.models import State, Submission
from server.submissions.position import QueuePlace, describe, expected_start, ordinal, queue_place
from testkit.factories import make_challenge, make_user, queue_submission

NOW = datetime(2026, 1, 1, 12, 0, tzinfo=UTC)


def test_ordinals_read_as_words_do() -> None:
    assert [ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22, 101, 111)] == [
        "1st",
        "2nd",
        "3rd",
        "4th",
        "11th",
        "12th",
        "13th",
        "21st",
        "22nd",
        "101st",
        "111th",
    ]


def test_the_place_is_said_in_words() -> None:
    assert describe(QueuePlace(position=3, ahead=2, expected_start_s=240)) == (
        "3rd in the queue, about 4 min"
    )
    assert describe(QueuePlace(position=1, ahead=0, expected_start_s=10)) == (
        "next in the queue, under a minute"
    )
    assert describe(QueuePlace(position=2, ahead=1, expected_start_s=None)) == "2nd in the queue"
    assert describe(QueuePlace(position=5, ahead=4, expected_start_s=7800)) == (
        "5th in the queue, about 2 h 10 min"
    )


def test_the_start_waits_for_a_free_slot_then_for_those_ahead() -> None:
    running = [(1, NOW - timedelta(seconds=60)), (1, NOW - timedelta(seconds=200))]
    # Two slots busy for 240 s and 100 s more; two ahead of 300 s each.
    start = expected_start(running=running, ahead=[1, 1], durations={1: 300.0}, slots=2, now=NOW)
    assert start == 400.0  # the second slot frees at 100, runs one to 400; the first frees at 240
    assert expected_start(running=[], ahead=[], durations={}, slots=1, now=NOW) == 0.0
    assert expected_start(running=running, ahead=[2], durations={1: 300.0}, slots=2, now=NOW) is (
        None
    )


def _finish(db: Session, submission: Submission, *, seconds: float) -> None:
    submission.state = State.SUCCEEDED
    submission.started_at = NOW - timedelta(seconds=seconds)
    submission.finished_at = NOW
    db.flush()


def test_a_queued_submission_knows_its_fair_place_and_start(db: Session) -> None:
    challenge = make_challenge(db, quota_concurrent=10, quota_per_day=50)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    done = queue_submission(db, alice, challenge)
    _finish(db, done, seconds=120)
    first = [queue_submission(db, alice, challenge) for _ in range(3)]
    later = queue_submission(db, bob, challenge)
    db.flush()
    # bob's comes second: users interleave in the claim order
    place = queue_place(db, submission=later, slots=1, max_running_per_user=2, now=NOW)
    assert place == QueuePlace(position=2, ahead=1, expected_start_s=120.0)
    third = queue_place(db, submission=first[1], slots=1, max_running_per_user=2, now=NOW)
    assert third is not None
    assert (third.position, third.expected_start_s) == (3, 240.0)
    assert queue_place(db, submission=done, slots=1, max_running_per_user=2) is None
