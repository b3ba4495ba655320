"""Fair claiming: users interleave, caps hold, and one attempt is never claimed twice."""

from __future__ import annotations

import threading
from collections import Counter

from hypothesis import given
from hypothesis import strategies as st
from sqlalchemy.orm import Session, joinedload, sessionmaker

from server.models import State, Submission
from server.submissions.work import claim_next, fair_order
from testkit.factories import make_challenge, make_user, queue_submission


def test_a_burst_from_one_user_does_not_starve_the_others() -> None:
    queued = [(1, 1, 7), (2, 1, 7), (3, 1, 7), (4, 1, 7), (5, 1, 8), (6, 1, 9)]
    order = fair_order(queued, Counter(), cap=10)
    assert [sid for sid, _ in order] == [1, 5, 6, 2, 3, 4]


def test_users_at_their_cap_wait() -> None:
    queued = [(1, 1, 7), (2, 1, 8), (3, 1, 7)]
    assert fair_order(queued, Counter({7: 2}), cap=2) == [(2, 1)]
    assert fair_order(queued, Counter({7: 1}), cap=2) == [(2, 1), (1, 1)]


@given(
    st.lists(st.integers(min_value=1, max_value=5), max_size=40),
    st.dictionaries(st.integers(1, 5), st.integers(0, 3)),
    st.integers(min_value=1, max_value=4),
)
def test_fair_order_properties(users: list[int], running: dict[int, int], cap: int) -> None:
    queued = [(i, 1, u) for i, u in enumerate(users)]
    order = fair_order(queued, Counter(running), cap)
    chosen = Counter(users[i] for i, _ in order)
    for user in set(users):
        assert running.get(user, 0) + chosen[user] <= max(cap, running.get(user, 0))
        mine = [i for i, _ in order if users[i] == user]
        assert mine == sorted(mine)  # each user's own submissions keep their order


def _queue(db: Session, n_per_user: dict[str, int]) -> None:
    challenge = make_challenge(db, quota_concurrent=100, quota_per_day=100)
    for name, n in n_per_user.items():
        user = make_user(db, name)
        for _ in range(n):
            queue_submission(db, user, challenge)
    db.commit()


def test_claim_next_interleaves_and_respects_the_cap(db: Session) -> None:
    _queue(db, {"alice": 3, "bob": 1})
    owners = []
    while (claimed := claim_next(db, worker="w1", max_running_per_user=2)) is not None:
        s = db.get(Submission, claimed[0], options=[joinedload(Submission.user)])
        assert s is not None
        assert s.state == State.LAUNCHING
        assert s.worker == "w1"  # who claimed it: a restarted w1 ends it at once
        owners.append(s.user.username)
    assert owners == ["alice", "bob", "alice"]  # alice's third waits for one of hers to end


def test_racing_workers_never_claim_the_same_attempt(
    committed_sessions: sessionmaker[Session],
) -> None:
    with committed_sessions() as db:
        _queue(db, {"alice": 4, "bob": 4})
    claims: list[tuple[int, int]] = []
    barrier = threading.Barrier(6)

    def worker() -> None:
        with committed_sessions() as db:
            barrier.wait()
            while (claimed := claim_next(db, worker="w", max_running_per_user=100)) is not None:
                claims.append(claimed)

    threads = [threading.Thread(target=worker) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(claims) == 8
    assert len(set(claims)) == 8
