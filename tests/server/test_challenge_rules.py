"""A phase's rules (docs/server.md, Challenge rules): best or last counts, a final choice, a
post-deadline board apart from the official one, a board hidden until published; and the
final choice and the close holding under concurrent writers on Postgres."""

from __future__ import annotations

import threading
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
from sqlalchemy import Engine, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from evaluator.suite import load_suite
from server import audit
from server.challenges.service import (
    ChallengeOptions,
    close_phase,
    get_challenge,
    get_phase,
    load_challenge,
    publish_board,
)
from server.kit.errors import Conflict, Invalid
from server.leaderboard.late import post_deadline_board
from server.leaderboard.snapshot import Snapshots
from server.leaderboard.visibility import as_seen_by
from server.models import Challenge, LeaderboardEntry, State, Submission, User
from server.submissions.final import mark_final
from server.submissions.reports import report_final, report_state
from testkit.factories import SUITE, make_user, queue_submission, result_doc

RULES = "counts: last, final_choice: true, after_close: post_deadline, board: hidden"


def rules_suite(directory: Path, rules: str = RULES) -> Path:
    """The server test suite with `rules` on its test phase."""
    path = directory / "server-tiny.yaml"
    path.write_text(
        SUITE.read_text().replace("seeds: {kind: secret}}", f"seeds: {{kind: secret}}, {rules}}}")
    )
    return path


def _challenge(db: Session, directory: Path, rules: str = RULES) -> Challenge:
    options = ChallengeOptions(quota_per_day=50, quota_concurrent=50)
    challenge = load_challenge(db, rules_suite(directory, rules), options, seed_secret="s" * 32)
    db.commit()
    return challenge


def _done(db: Session, user: User, challenge: Challenge, successes: list[bool]) -> Submission:
    s = queue_submission(db, user, challenge, "test")
    assert report_state(db, s.id, 1, State.LAUNCHING, "starting")
    assert report_state(db, s.id, 1, State.RUNNING, "evaluating")
    result = result_doc(successes, phase="test")
    assert report_final(db, s.id, 1, State.SUCCEEDED, "done", result=result)
    db.commit()
    return s


def _row_of(db: Session, user: User) -> int | None:
    return db.scalar(
        select(LeaderboardEntry.submission_id).where(LeaderboardEntry.user_id == user.id)
    )


def test_rules_are_not_part_of_the_suites_hash(tmp_path: Path) -> None:
    assert load_suite(rules_suite(tmp_path)).sha256() == load_suite(SUITE).sha256()


def test_the_phase_stores_the_suites_rules(db: Session, tmp_path: Path) -> None:
    challenge = _challenge(db, tmp_path)
    test = next(p for p in challenge.phases if p.name == "test")
    dev = next(p for p in challenge.phases if p.name == "dev")
    assert (test.counts, test.final_choice, test.after_close, test.board) == (
        "last",
        True,
        "post_deadline",
        "hidden",
    )
    assert (dev.counts, dev.final_choice, dev.after_close, dev.board) == (
        "best",
        False,
        "refuse",
        "public",
    )


def test_a_load_is_audited_with_what_it_changed_and_a_reload_of_the_same_is_not(
    db: Session, tmp_path: Path
) -> None:
    challenge = _challenge(db, tmp_path)
    (created,) = audit.records(db, action="challenge.load")
    assert (created.target_kind, created.target_id, created.challenge_id) == (
        "challenge",
        challenge.id,
        challenge.id,
    )
    assert created.actor.startswith("cli:")
    assert created.actor_id is None
    assert created.detail is not None
    assert created.detail["new"]["suite_sha256"] == challenge.suite_hash
    assert created.detail["new"]["quota_per_day"] == 50
    assert created.detail["new"]["phase test"]["counts"] == "last"
    assert created.detail["old"]["phase test"] is None  # a new challenge: nothing before
    assert {name for name in created.detail["new"] if name.startswith("phase ")} == {
        "phase dev",
        "phase test",
    }

    _challenge(db, tmp_path)  # the same suite, the same options
    assert len(audit.records(db, action="challenge.load")) == 1

    options = ChallengeOptions(quota_per_day=7, quota_concurrent=50)
    load_challenge(db, rules_suite(tmp_path, "counts: best"), options, seed_secret="s" * 32)
    changed = audit.records(db, action="challenge.load")[0]
    assert changed.detail is not None
    assert (
        set(changed.detail["old"])
        == set(changed.detail["new"])
        == {
            "quota_per_day",
            "phase test",  # only the phase that changed
        }
    )
    assert (changed.detail["old"]["quota_per_day"], changed.detail["new"]["quota_per_day"]) == (
        50,
        7,
    )
    was, now = changed.detail["old"]["phase test"], changed.detail["new"]["phase test"]
    assert (was["counts"], was["board"], now["counts"], now["board"]) == (
        "last",
        "hidden",
        "best",
        "public",
    )


def test_a_reload_with_dates_in_another_zone_is_the_same_load(
    sessions: sessionmaker[Session], tmp_path: Path
) -> None:
    opens = datetime(2027, 1, 31, 12, 0, tzinfo=timezone(timedelta(hours=2)))
    options = ChallengeOptions(opens={"test": opens})
    for _ in range(2):  # each in a session of its own: the second reads the dates back
        with sessions() as db:
            load_challenge(db, rules_suite(tmp_path), options, seed_secret="s" * 32)
            db.commit()
    with sessions() as db:
        (loaded,) = audit.records(db, action="challenge.load")
        assert loaded.detail is not None
        assert loaded.detail["new"]["phase test"]["opens_at"] == "2027-01-31T10:00:00+00:00"
        test = get_phase(get_challenge(db, slug="server-tiny"), "test")
        assert test.opens_at == opens


def test_joining_a_group_and_sharing_its_quota_are_in_the_load_record(
    sessions: sessionmaker[Session], tmp_path: Path
) -> None:
    track = tmp_path / "server-tiny-visual.yaml"
    track.write_text(SUITE.read_text().replace("name: server-tiny", "name: server-tiny-visual"))
    with sessions() as db:
        load_challenge(db, SUITE, ChallengeOptions(track="state"), seed_secret="s" * 32)
        joined = ChallengeOptions(track="visual", track_of="server-tiny", quota_shared=True)
        load_challenge(db, track, joined, seed_secret="s" * 32)
        db.commit()
        record = audit.records(db, action="challenge.load")[0]
        assert record.detail is not None
        new = record.detail["new"]
        assert (new["track"], new["track_of"], new["quota_shared"]) == (
            "visual",
            "server-tiny",
            True,
        )
        load_challenge(db, track, ChallengeOptions(quota_shared=False), seed_secret="s" * 32)
        record = audit.records(db, action="challenge.load")[0]
        assert record.detail == {"old": {"quota_shared": True}, "new": {"quota_shared": False}}


@pytest.mark.parametrize(
    ("quotas", "named"),
    [({"quota_per_day": 0}, "quota_per_day"), ({"quota_concurrent": 10_001}, "quota_concurrent")],
)
def test_a_load_refuses_the_quotas_the_console_refuses(
    db: Session, tmp_path: Path, quotas: dict[str, int], named: str
) -> None:
    with pytest.raises(Invalid, match=f"{named} must be a whole number from 1 to 10000") as refused:
        load_challenge(db, rules_suite(tmp_path), ChallengeOptions(**quotas), seed_secret="s" * 32)
    assert set(refused.value.fields or {}) == {named}


def test_the_last_submission_counts_where_the_phase_says_last(db: Session, tmp_path: Path) -> None:
    challenge = _challenge(db, tmp_path)
    alice = make_user(db, "alice")
    _done(db, alice, challenge, [True, True])
    last = _done(db, alice, challenge, [False, True])
    assert _row_of(db, alice) == last.id


def test_the_final_choice_is_the_row_and_its_mark_moves(db: Session, tmp_path: Path) -> None:
    challenge = _challenge(db, tmp_path)
    alice = make_user(db, "alice")
    first = _done(db, alice, challenge, [True, True])
    second = _done(db, alice, challenge, [False, True])
    mark_final(db, user=alice, submission=first, final=True)
    db.commit()
    assert _row_of(db, alice) == first.id
    mark_final(db, user=alice, submission=second, final=True)
    db.commit()
    assert (first.final_for, second.final_for) == (None, f"user:{alice.id}")
    mark_final(db, user=alice, submission=second, final=False)
    db.commit()
    assert second.final_for is None
    assert _row_of(db, alice) == second.id  # the last, again


def test_a_phase_without_a_final_choice_refuses_a_mark(db: Session, tmp_path: Path) -> None:
    challenge = _challenge(db, tmp_path)
    alice = make_user(db, "alice")
    s = queue_submission(db, alice, challenge, "dev")
    with pytest.raises(Conflict, match="takes no final choice"):
        mark_final(db, user=alice, submission=s, final=True)


def test_the_database_holds_one_final_choice_per_participant(db: Session, tmp_path: Path) -> None:
    challenge = _challenge(db, tmp_path)
    alice = make_user(db, "alice")
    a, b = (queue_submission(db, alice, challenge, "test") for _ in range(2))
    a.final_for = b.final_for = f"user:{alice.id}"
    with pytest.raises(IntegrityError):
        db.flush()
    db.rollback()


def test_after_the_close_a_submission_goes_to_the_post_deadline_board(
    db: Session, tmp_path: Path
) -> None:
    challenge = _challenge(db, tmp_path)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    on_time = _done(db, alice, challenge, [True, False])
    close_phase(db, by=None, slug=challenge.slug, phase="test")
    db.commit()
    late = _done(db, bob, challenge, [True, True])
    assert late.post_deadline
    assert not on_time.post_deadline
    assert _row_of(db, bob) is None  # never on the official board
    with pytest.raises(Conflict, match="came after the deadline"):
        mark_final(db, user=bob, submission=late, final=True)
    with pytest.raises(Conflict, match="closed at"):
        mark_final(db, user=alice, submission=on_time, final=True)
    publish_board(db, by=None, slug=challenge.slug, phase="test")
    rows = post_deadline_board(db, slug=challenge.slug, phase="test", viewer=None)
    assert [(r.rank, r.submission_id) for r in rows] == [(1, late.id)]


def test_after_the_close_a_phase_that_refuses_late_ones_refuses(
    db: Session, tmp_path: Path
) -> None:
    challenge = _challenge(db, tmp_path, rules="after_close: refuse")
    close_phase(db, by=None, slug=challenge.slug, phase="test")
    db.commit()
    with pytest.raises(Conflict, match="closed at"):
        queue_submission(db, make_user(db, "alice"), challenge, "test")


def test_a_hidden_board_shows_each_their_own_rows_until_published(
    db: Session, tmp_path: Path
) -> None:
    challenge = _challenge(db, tmp_path)
    alice, bob = make_user(db, "alice"), make_user(db, "bob")
    organizer = make_user(db, "organizer", admin=True)
    mine = _done(db, alice, challenge, [True, False])
    _done(db, bob, challenge, [True, True])
    boards = Snapshots(max_age=0)
    board = boards.current_in(db, slug=challenge.slug, phase="test")
    assert board.hidden
    assert as_seen_by(db, board, user=None).total == 0
    alices = as_seen_by(db, board, user=alice)
    assert [(s.submission_id, alices.place(0)[0]) for s in alices.rows] == [(mine.id, None)]
    assert as_seen_by(db, board, user=organizer).total == 2
    publish_board(db, by=None, slug=challenge.slug, phase="test")
    db.commit()
    board = boards.current_in(db, slug=challenge.slug, phase="test")
    assert not board.hidden
    assert as_seen_by(db, board, user=None).total == 2


# Postgres alone: SQLite runs one writer at a time, so there is no race to lose there.
@pytest.mark.parametrize("engine", ["postgres"], indirect=True)
def test_marks_made_at_once_leave_one_final_choice(
    engine: Engine, committed_sessions: sessionmaker[Session], tmp_path: Path
) -> None:
    with committed_sessions() as db:
        challenge = _challenge(db, tmp_path)
        alice = make_user(db, "alice")
        ids = [_done(db, alice, challenge, [True, i % 2 == 0]).id for i in range(4)]
        alice_id = alice.id
    barrier = threading.Barrier(len(ids))
    errors: list[BaseException] = []

    def mark(submission_id: int) -> None:
        try:
            with committed_sessions() as db:
                user = db.get(User, alice_id)
                submission = db.get(Submission, submission_id)
                assert user is not None
                assert submission is not None
                barrier.wait()
                mark_final(db, user=user, submission=submission, final=True)
                db.commit()
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=mark, args=(i,)) for i in ids]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert errors == []
    with committed_sessions() as db:
        finals = db.scalars(select(Submission.id).where(Submission.final_for.is_not(None))).all()
        assert len(finals) == 1
        row = db.scalar(select(LeaderboardEntry.submission_id))
        assert row == finals[0]  # the board follows the mark that stood


@pytest.mark.parametrize("engine", ["postgres"], indirect=True)
def test_participants_marking_at_once_each_keep_their_own_choice(
    engine: Engine, committed_sessions: sessionmaker[Session], tmp_path: Path
) -> None:
    with committed_sessions() as db:
        challenge = _challenge(db, tmp_path)
        users = [make_user(db, f"user{i}") for i in range(4)]
        made = {u.id: [_done(db, u, challenge, [True, False]).id for _ in range(2)] for u in users}
    barrier = threading.Barrier(len(made))
    errors: list[BaseException] = []

    def mark(user_id: int, submission_id: int) -> None:
        try:
            with committed_sessions() as db:
                user = db.get(User, user_id)
                submission = db.get(Submission, submission_id)
                assert user is not None
                assert submission is not None
                barrier.wait()
                mark_final(db, user=user, submission=submission, final=True)
                db.commit()
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=mark, args=(u, ids[0])) for u, ids in made.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert errors == []  # no deadlock between marks of different participants
    with committed_sessions() as db:
        finals = set(db.scalars(select(Submission.id).where(Submission.final_for.is_not(None))))
        assert finals == {ids[0] for ids in made.values()}
        rows = set(db.scalars(select(LeaderboardEntry.submission_id)))
        assert rows == finals


@pytest.mark.parametrize("engine", ["postgres"], indirect=True)
def test_no_official_submission_lands_after_the_close(
    engine: Engine, committed_sessions: sessionmaker[Session], tmp_path: Path
) -> None:
    with committed_sessions() as db:
        challenge = _challenge(db, tmp_path)
        users = [make_user(db, f"user{i}").id for i in range(4)]
        slug = challenge.slug
    submitted = threading.Event()
    closed = threading.Event()
    errors: list[BaseException] = []

    def keep_submitting(user_id: int) -> None:
        try:
            for _ in range(40):
                with committed_sessions() as db:
                    user = db.get(User, user_id)
                    assert user is not None
                    queue_submission(db, user, get_challenge(db, slug=slug), "test")
                    db.commit()
                submitted.set()
                if closed.is_set():
                    return  # one more after the close: it is late
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=keep_submitting, args=(u,)) for u in users]
    for t in threads:
        t.start()
    assert submitted.wait(timeout=60)
    with committed_sessions() as db:
        phase = close_phase(db, by=None, slug=slug, phase="test")
        db.commit()
        closes_at = phase.closes_at
    closed.set()

    def official(db: Session) -> int:
        return db.scalar(select(func.count()).where(Submission.post_deadline.is_(False))) or 0

    with committed_sessions() as db:
        at_close = official(db)
    for t in threads:
        t.join(timeout=120)
    assert errors == []
    with committed_sessions() as db:
        assert official(db) == at_close  # none landed on the official board after it
        made = db.execute(select(Submission.created_at, Submission.post_deadline)).all()
        assert closes_at is not None
        assert all(late == (at >= closes_at) for at, late in made)
        assert any(late for _, late in made)
