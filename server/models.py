"""The database schema (SQLAlchemy 2.0 typed models).

Alembic migrations in ``alembic/versions`` are the only way this schema reaches a database;
``alembic check`` in the tests proves the two agree.
"""

from __future__ import annotations

import enum
from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Enum,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite stores naive values)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime; use server.models.utcnow()")
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        datetime: UTCDateTime(),
        dict[str, Any]: JSON(),
    }


class State(enum.StrEnum):
    QUEUED = "queued"
    LAUNCHING = "launching"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"  # the policy's fault
    ERROR = "error"  # ours
    CANCELLED = "cancelled"
    TIMED_OUT = "timed_out"

    @property
    def final(self) -> bool:
        return self in FINAL_STATES


FINAL_STATES = frozenset(
    {State.SUCCEEDED, State.FAILED, State.ERROR, State.CANCELLED, State.TIMED_OUT}
)
ACTIVE_STATES = frozenset({State.QUEUED, State.LAUNCHING, State.RUNNING})
# What counts against a quota: work the participant caused. Our errors and cancels do not.
QUOTA_STATES = frozenset({State.RUNNING, State.SUCCEEDED, State.FAILED, State.TIMED_OUT})

_state_enum = Enum(
    State, name="submission_state", values_callable=lambda e: [m.value for m in e], length=16
)


class User(Base):
    __tablename__ = "users"

    id: Mapped[int] = mapped_column(primary_key=True)
    username: Mapped[str] = mapped_column(String(32), unique=True)
    email: Mapped[str] = mapped_column(String(254), unique=True)
    password_hash: Mapped[str] = mapped_column(String(256))
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class ApiToken(Base):
    __tablename__ = "api_tokens"

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(64))
    prefix: Mapped[str] = mapped_column(String(16), unique=True)
    digest: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_used_at: Mapped[datetime | None]
    revoked_at: Mapped[datetime | None]

    user: Mapped[User] = relationship()


class Session(Base):
    __tablename__ = "sessions"

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    prefix: Mapped[str] = mapped_column(String(16), unique=True)
    digest: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]

    user: Mapped[User] = relationship()


class Challenge(Base):
    __tablename__ = "challenges"

    id: Mapped[int] = mapped_column(primary_key=True)
    slug: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    suite_yaml: Mapped[str] = mapped_column(Text)
    suite_hash: Mapped[str] = mapped_column(String(64))
    quota_per_day: Mapped[int] = mapped_column(Integer, default=5)
    quota_concurrent: Mapped[int] = mapped_column(Integer, default=1)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)

    phases: Mapped[list[Phase]] = relationship(
        back_populates="challenge", order_by="Phase.id", cascade="all, delete-orphan"
    )


class Phase(Base):
    __tablename__ = "phases"
    __table_args__ = (UniqueConstraint("challenge_id", "name"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    challenge_id: Mapped[int] = mapped_column(ForeignKey("challenges.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(32))
    public_seeds: Mapped[bool] = mapped_column(Boolean)
    seed_commitment: Mapped[str] = mapped_column(String(64))
    opens_at: Mapped[datetime | None]
    closes_at: Mapped[datetime | None]
    leaderboard_version: Mapped[int] = mapped_column(Integer, default=0)
    """Bumped whenever the phase's leaderboard changes: the key of the API's cache."""

    challenge: Mapped[Challenge] = relationship(back_populates="phases")

    def is_open(self, now: datetime) -> bool:
        return (self.opens_at is None or self.opens_at <= now) and (
            self.closes_at is None or now < self.closes_at
        )


class Submission(Base):
    __tablename__ = "submissions"
    __table_args__ = (
        Index("ix_submissions_user_created", "user_id", "created_at"),
        Index("ix_submissions_state", "state"),
        Index("ix_submissions_phase_user", "phase_id", "user_id"),
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
    public: Mapped[bool] = mapped_column(Boolean, default=True)
    hidden: Mapped[bool] = mapped_column(Boolean, default=False)
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
    score: Mapped[float | None] = mapped_column(Float)
    progress: Mapped[dict[str, Any] | None]
    """The worker's last progress report: episodes done and planned, current task."""
    log_tail: Mapped[str] = mapped_column(Text, default="")
    result: Mapped[dict[str, Any] | None]
    """The evaluator's result document of the current attempt (schema evaluator.results)."""

    user: Mapped[User] = relationship()
    challenge: Mapped[Challenge] = relationship()
    phase: Mapped[Phase] = relationship()


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
    success_at_end: Mapped[bool] = mapped_column(Boolean)
    steps: Mapped[int] = mapped_column(Integer)
    episode_return: Mapped[float] = mapped_column(Float)
    wall_time_s: Mapped[float] = mapped_column(Float)
    invalid_actions: Mapped[int] = mapped_column(Integer)
    clipped_actions: Mapped[int] = mapped_column(Integer)
    failure: Mapped[str | None] = mapped_column(String(2000))


class LeaderboardEntry(Base):
    """One row of a phase's leaderboard: a user's best public succeeded submission, or a
    submission an admin flagged as a baseline (each baseline is its own row).

    Maintained by ``server.leaderboard.refresh`` whenever one of its inputs changes, so that
    reading a leaderboard is one indexed range scan however many submissions exist.
    """

    __tablename__ = "leaderboard_entries"
    __table_args__ = (
        # owner_key is the user id for regular rows and NULL for baselines: at most one
        # regular row per user and phase, any number of baselines.
        UniqueConstraint("phase_id", "owner_key"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    phase_id: Mapped[int] = mapped_column(ForeignKey("phases.id", ondelete="CASCADE"))
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), unique=True
    )
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    owner_key: Mapped[int | None] = mapped_column(Integer)
    baseline: Mapped[bool] = mapped_column(Boolean)
    score: Mapped[float] = mapped_column(Float)
    submitted_at: Mapped[datetime]
    username: Mapped[str] = mapped_column(String(32))
    summary: Mapped[dict[str, Any]]
    """Per-condition scores and per-task success with intervals, as the leaderboard shows."""


Index(
    "ix_leaderboard_rank",
    LeaderboardEntry.phase_id,
    LeaderboardEntry.score.desc(),
    LeaderboardEntry.submitted_at,
    LeaderboardEntry.id,
)


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
