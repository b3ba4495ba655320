"""Where a queued submission stands: its place in the order workers claim work (the fair order
of :func:`server.submissions.work.fair_order`) and when it is expected to start, from the
evaluations running now and how long the challenges' recent evaluations took."""

from __future__ import annotations

import heapq
import statistics
from collections import Counter
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.kit.settings import Settings
from server.models import State, Submission, utcnow
from server.submissions.schemas import QueueOut
from server.submissions.work import fair_order

RECENT = 20  # evaluations per challenge the expected duration is the median of
MAX_QUEUED = 2000  # what is ranked; a queue longer than this is shown as "over 2000"
ENDED_BY_POLICY_OR_RESULT = (State.SUCCEEDED, State.FAILED, State.TIMED_OUT)


@dataclass(frozen=True)
class QueuePlace:
    position: int
    """1: the next submission a free worker claims."""
    ahead: int
    expected_start_s: float | None
    """Seconds from now; None while the challenges ahead have no finished evaluations yet."""


def queue_place(
    db: DB,
    *,
    submission: Submission,
    slots: int,
    max_running_per_user: int,
    now: datetime | None = None,
) -> QueuePlace | None:
    """The place of a `queued` submission (None in any other state). `slots` is how many
    evaluations run at once (the embedded worker's threads; 0 when unknown: as many as run)."""
    if submission.state != State.QUEUED:
        return None
    now = now or utcnow()
    queued = [
        (sid, attempt, user, challenge)
        for sid, attempt, user, challenge in db.execute(
            select(Submission.id, Submission.attempt, Submission.user_id, Submission.challenge_id)
            .where(Submission.state == State.QUEUED)
            .order_by(Submission.updated_at, Submission.id)
            .limit(MAX_QUEUED)
        )
    ]
    running = [
        (user, challenge, started)
        for user, challenge, started in db.execute(
            select(Submission.user_id, Submission.challenge_id, Submission.started_at).where(
                Submission.state.in_([State.LAUNCHING, State.RUNNING])
            )
        )
    ]
    order = [sid for sid, _ in claim_order(queued, running, max_running_per_user)]
    if submission.id not in order:
        return QueuePlace(position=len(order) + 1, ahead=len(order), expected_start_s=None)
    ahead = order.index(submission.id)
    challenge_of = {sid: challenge for sid, _, _, challenge in queued}
    durations = recent_durations(
        db, challenge_ids={c for _, c, _ in running} | {challenge_of[s] for s in order[:ahead]}
    )
    start = expected_start(
        running=[(c, started) for _, c, started in running],
        ahead=[challenge_of[s] for s in order[:ahead]],
        durations=durations,
        slots=max(slots, len(running), 1),
        now=now,
    )
    return QueuePlace(position=ahead + 1, ahead=ahead, expected_start_s=start)


def claim_order(
    queued: list[tuple[int, int, int, int]],
    running: list[tuple[int, int, datetime | None]],
    cap: int,
) -> list[tuple[int, int]]:
    """The fair order, then those whose owner is at the cap, in the order they queued."""
    per_user = Counter(user for user, _, _ in running)
    order = fair_order([(s, a, u) for s, a, u, _ in queued], per_user, cap)
    placed = set(order)
    return order + [(s, a) for s, a, _, _ in queued if (s, a) not in placed]


def recent_durations(db: DB, *, challenge_ids: set[int]) -> dict[int, float]:
    """Each challenge's median evaluation time (seconds) over its last evaluations."""
    found: dict[int, float] = {}
    for challenge_id in challenge_ids:
        rows = db.execute(
            select(Submission.started_at, Submission.finished_at)
            .where(
                Submission.challenge_id == challenge_id,
                Submission.state.in_(ENDED_BY_POLICY_OR_RESULT),
                Submission.started_at.is_not(None),
                Submission.finished_at.is_not(None),
            )
            .order_by(Submission.finished_at.desc())
            .limit(RECENT)
        ).all()
        times = [(end - start).total_seconds() for start, end in rows if start and end]
        if times:
            found[challenge_id] = max(0.0, statistics.median(times))
    return found


def expected_start(
    *,
    running: list[tuple[int, datetime | None]],
    ahead: list[int],
    durations: dict[int, float],
    slots: int,
    now: datetime,
) -> float | None:
    """Seconds until a slot is free for the submission after `ahead` (challenge ids, in claim
    order), with `running` (challenge, started) in `slots` slots. Pure, for testing."""
    free: list[float] = []
    for challenge, started in running:
        if challenge not in durations:
            return None
        elapsed = (now - started).total_seconds() if started is not None else 0.0
        free.append(max(0.0, durations[challenge] - elapsed))
    free += [0.0] * max(0, slots - len(free))
    heapq.heapify(free)
    for challenge in ahead:
        if challenge not in durations:
            return None
        heapq.heappush(free, heapq.heappop(free) + durations[challenge])
    return free[0]


def ordinal(n: int) -> str:
    """1st, 2nd, 3rd, 4th, 11th, 21st."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def about(seconds: float) -> str:
    """A rough duration: "under a minute", "about 4 min", "about 2 h 10 min"."""
    if seconds < 60:
        return "under a minute"
    minutes = round(seconds / 60)
    if minutes < 60:
        return f"about {minutes} min"
    return f"about {minutes // 60} h {minutes % 60:02d} min"


def describe(place: QueuePlace) -> str:
    """ "3rd in the queue, about 4 min" (or "next in the queue, under a minute")."""
    where = (
        "next in the queue" if place.position == 1 else f"{ordinal(place.position)} in the queue"
    )
    if place.expected_start_s is None:
        return where
    return f"{where}, {about(place.expected_start_s)}"


def queue_out(db: DB, *, submission: Submission, settings: Settings) -> QueueOut | None:
    """The API's view of `queue_place` with this server's worker slots."""
    place = queue_place(
        db,
        submission=submission,
        slots=settings.inline_workers if settings.queue == "inline" else 0,
        max_running_per_user=settings.max_running_per_user,
    )
    if place is None:
        return None
    return QueueOut(
        position=place.position,
        ahead=place.ahead,
        expected_start_s=place.expected_start_s,
        text=describe(place),
    )
