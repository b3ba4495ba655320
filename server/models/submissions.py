"""Submissions: their state, the transitions between states, their results, and the outbox of
work for the queue."""

from __future__ import annotations

import enum
from datetime import datetime
from typing import Any

from sqlalchemy import (
    BigInteger,
    Boolean,
    CheckConstraint,
    Enum,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    false,
)
from sqlalchemy.orm import Mapped, mapped_column, relationship

from internal_api.schemas import ErrorCause, State
from server.models.accounts import User
from server.models.base import Base, utcnow
from server.models.challenges import Challenge, Phase


class Cause(enum.StrEnum):
    """Why an attempt ended `error` through no fault of the policy's, where the reconciler acts
    on it (a lost attempt runs again once, a stopped one always): a typed column, never text to
    match. The causes a worker reports are the contract's `ErrorCause`, recorded as its value;
    the server finds the others itself."""

    WORKER_LOST = "worker_lost"
    WORKER_RESTARTED = "worker_restarted"
    CLUSTER = ErrorCause.CLUSTER.value
    """The Kubernetes cluster stopped it (evicted, preempted, unschedulable, quota, node lost)."""
    STOPPED = "stopped"
    """The service was stopped (Ctrl-C, SIGTERM) while it ran: queued again, every time."""
    CONFIGURATION = ErrorCause.CONFIGURATION.value
    """The operator's configuration cannot run it (the challenge's evaluator image is not one
    the workers may run): not queued again, which would fail alike until it is changed."""


_state_enum = Enum(
    State, name="submission_state", values_callable=lambda e: [m.value for m in e], length=16
)
_cause_enum = Enum(
    Cause, name="transition_cause", values_callable=lambda e: [m.value for m in e], length=32
)


class Submission(Base):
    __tablename__ = "submissions"
    __table_args__ = (
        Index("ix_submissions_user_created", "user_id", "created_at"),
        Index("ix_submissions_state", "state"),
        Index("ix_submissions_phase_user", "phase_id", "user_id"),
        # One final choice per participant (or team) and phase: of two marks made at once one
        # stands, whatever the code above does. NULLs (not a final choice) never collide.
        Index("uq_submissions_final", "phase_id", "final_for", unique=True),
        CheckConstraint("attempt >= 1", name="attempt_positive"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"))
    challenge_id: Mapped[int] = mapped_column(ForeignKey("challenges.id", ondelete="CASCADE"))
    phase_id: Mapped[int] = mapped_column(ForeignKey("phases.id", ondelete="CASCADE"))
    image: Mapped[str] = mapped_column(String(512))
    """What the participant submitted (a tag reference, or ``local:NAME`` in the demo)."""
    pinned_image: Mapped[str] = mapped_column(String(512))
    """What runs: ``domain/path@sha256:...`` resolved at submit time, or ``local:NAME``."""
    image_bytes: Mapped[int | None] = mapped_column(BigInteger)
    description: Mapped[str] = mapped_column(String(2000), default="")
    method: Mapped[str | None] = mapped_column(String(100))
    """The method's name, as the leaderboard shows it (optional)."""
    paper_url: Mapped[str | None] = mapped_column(String(500))
    """An http(s) link to the method's paper (optional)."""
    code_url: Mapped[str | None] = mapped_column(String(500))
    """An http(s) link to the method's code (optional)."""
    team_id: Mapped[int | None] = mapped_column(
        ForeignKey("teams.id", ondelete="SET NULL"), index=True
    )
    """The submitter's team when it was made: it stays the team's (docs/server.md, Teams)."""
    public: Mapped[bool] = mapped_column(Boolean, default=True)
    hidden: Mapped[bool] = mapped_column(Boolean, default=False)
    """Taken off every board by an organizer (`moderation_reason` says why)."""
    disqualified: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    """Ruled out by an organizer: it stays on the board, unranked, with `moderation_reason`."""
    moderation_reason: Mapped[str | None] = mapped_column(String(2000))
    """Why an organizer hid or disqualified it, as the board and its page show; None: never."""
    baseline: Mapped[bool] = mapped_column(Boolean, default=False)
    state: Mapped[State] = mapped_column(_state_enum, default=State.QUEUED)
    reason: Mapped[str] = mapped_column(String(2000), default="")
    attempt: Mapped[int] = mapped_column(Integer, default=1)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    heartbeat_at: Mapped[datetime | None]
    deadline_at: Mapped[datetime | None]
    worker: Mapped[str | None] = mapped_column(String(200))
    """The worker that claimed the current attempt (its `MANIEVAL_WORKER_NAME`)."""
    score: Mapped[float | None] = mapped_column(Float)
    progress: Mapped[dict[str, Any] | None]
    """The worker's last progress report: episodes done and planned, current task."""
    log_tail: Mapped[str] = mapped_column(Text, default="")
    result: Mapped[dict[str, Any] | None]
    """The evaluator's result document of the current attempt (schema evaluator.results)."""
    board_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    """The phase's board version this submission counts for (docs/server.md, Re-evaluation)."""
    reevaluation_of: Mapped[int | None] = mapped_column(Integer, index=True)
    """The participant's own submission this one re-evaluates for `board_version`; None for a
    participant's own. No foreign key: SQLite adds one only by rebuilding `submissions`, which
    cascades into every table that refers to it (alembic 0012); a re-evaluation has its
    original's owner, and goes with them."""

    post_deadline: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    """Made after its phase closed: it stands on the post-deadline board, never on the official
    one (docs/server.md, Challenge rules)."""
    final_for: Mapped[str | None] = mapped_column(String(32))
    """Whose final choice in its phase this submission is ("user:ID", or "team:ID" in team
    mode), or None: unique per phase (`uq_submissions_final`)."""

    user: Mapped[User] = relationship(lazy="raise")
    challenge: Mapped[Challenge] = relationship(lazy="raise")
    phase: Mapped[Phase] = relationship(lazy="raise")


class Transition(Base):
    __tablename__ = "transitions"

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), index=True
    )
    attempt: Mapped[int] = mapped_column(Integer)
    from_state: Mapped[State | None] = mapped_column(_state_enum)
    to_state: Mapped[State] = mapped_column(_state_enum)
    reason: Mapped[str] = mapped_column(String(2000), default="")
    cause: Mapped[Cause | None] = mapped_column(_cause_enum)
    at: Mapped[datetime] = mapped_column(default=utcnow)


class TaskResultRow(Base):
    __tablename__ = "task_results"
    __table_args__ = (UniqueConstraint("submission_id", "attempt", "condition", "env_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    attempt: Mapped[int] = mapped_column(Integer)
    condition: Mapped[str] = mapped_column(String(32))
    env_id: Mapped[str] = mapped_column(String(64))
    episodes: Mapped[int] = mapped_column(Integer)
    """Planned."""
    episodes_ran: Mapped[int] = mapped_column(Integer)
    """Those that ran, in whole or in part (`evaluator.results.ran`): all of them once the
    evaluation completed; only these have episode rows. The rate and its interval are over
    the planned ones, so they mean something only when every planned episode ran."""
    successes: Mapped[int] = mapped_column(Integer)
    success_rate: Mapped[float] = mapped_column(Float)
    ci_low: Mapped[float] = mapped_column(Float)
    ci_high: Mapped[float] = mapped_column(Float)
    mean_steps: Mapped[float] = mapped_column(Float)


class EpisodeResultRow(Base):
    __tablename__ = "episode_results"
    __table_args__ = (UniqueConstraint("task_result_id", "index"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    task_result_id: Mapped[int] = mapped_column(ForeignKey("task_results.id", ondelete="CASCADE"))
    index: Mapped[int] = mapped_column(Integer)
    seed: Mapped[int] = mapped_column(BigInteger)
    success_once: Mapped[bool] = mapped_column(Boolean)
    success_at_end: Mapped[bool | None] = mapped_column(Boolean)
    """None: not measured (the suite stops an episode at its first success)."""
    steps: Mapped[int] = mapped_column(Integer)
    episode_return: Mapped[float] = mapped_column(Float)
    wall_time_s: Mapped[float] = mapped_column(Float)
    invalid_actions: Mapped[int] = mapped_column(Integer)
    clipped_actions: Mapped[int] = mapped_column(Integer)
    failure: Mapped[str | None] = mapped_column(String(2000))


class Outbox(Base):
    """Work to hand to the queue, written in the same transaction as the state it acts on.

    The dispatcher sends rows after the commit and marks them sent; a crash between the commit
    and the broker leaves the row unsent, and the next dispatch picks it up.
    """

    __tablename__ = "outbox"
    __table_args__ = (Index("ix_outbox_pending", "sent_at", "id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    attempt: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    sent_at: Mapped[datetime | None]
