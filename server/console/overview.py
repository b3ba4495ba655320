"""What the admin home shows: every challenge grouped with its tracks, its phases' status, its
submissions by state and how many are stuck, and the latest audit records."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from datetime import datetime
from typing import Literal

from sqlalchemy import func, select
from sqlalchemy.orm import Session as DB

from server.challenges.service import all_challenges
from server.challenges.tracks import track_name
from server.models import Challenge, Phase, State, Submission
from server.submissions.reconcile import Timeouts, stuck

PhaseStatus = Literal["open", "closed", "upcoming"]


def phase_status(phase: Phase, now: datetime) -> PhaseStatus:
    """Whether the phase takes submissions now, has not opened yet, or has closed."""
    if phase.is_open(now):
        return "open"
    return "closed" if phase.has_opened(now) else "upcoming"


@dataclass(frozen=True)
class ChallengeSummary:
    """One challenge (or track) on the admin home."""

    challenge: Challenge
    track: str
    """Its name in its group of tracks (its slug when alone)."""
    phases: list[tuple[Phase, PhaseStatus]]
    by_state: dict[str, int]
    """Its submissions in each state, in the state machine's order; only states it has."""
    stuck: int

    @property
    def total(self) -> int:
        return sum(self.by_state.values())


@dataclass(frozen=True)
class Group:
    """A head challenge and its tracks (just itself when it has none)."""

    head: ChallengeSummary
    tracks: list[ChallengeSummary]


def overview(db: DB, *, timeouts: Timeouts, now: datetime) -> list[Group]:
    """Every challenge, grouped under the head of its tracks, oldest first."""
    counts: Counter[tuple[int, str]] = Counter()
    for challenge_id, state, n in db.execute(
        select(Submission.challenge_id, Submission.state, func.count()).group_by(
            Submission.challenge_id, Submission.state
        )
    ):
        counts[challenge_id, State(state).value] = n
    stuck_by = dict(
        db.execute(
            select(Submission.challenge_id, func.count())
            .where(stuck(timeouts, now))
            .group_by(Submission.challenge_id)
        ).all()
    )

    def summary(challenge: Challenge) -> ChallengeSummary:
        by_state = {
            s.value: counts[challenge.id, s.value] for s in State if counts[challenge.id, s.value]
        }
        return ChallengeSummary(
            challenge=challenge,
            track=track_name(challenge),
            phases=[(p, phase_status(p, now)) for p in challenge.phases],
            by_state=by_state,
            stuck=stuck_by.get(challenge.id, 0),
        )

    challenges = all_challenges(db)
    ids = {c.id for c in challenges}
    heads = [c for c in challenges if c.track_of is None or c.track_of not in ids]
    return [
        Group(
            head=summary(head),
            tracks=[summary(c) for c in challenges if c.track_of == head.id and c is not head],
        )
        for head in heads
    ]
