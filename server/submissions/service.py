"""Submissions: accept, quota, who may see what, cancel and edit; and the reads the API and
the pages show (lists, timelines, results). An organizer's actions on them (re-run, hide,
disqualify) are :mod:`server.submissions.moderation`.

State changes go through :mod:`server.submissions.states`; work for the queue is written to the
``outbox`` in the same transaction and sent after the commit (:mod:`server.submissions.outbox`).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import joinedload

from evaluator import results
from evaluator.bundled import LOCAL_PREFIX
from server.challenges.quota import check_quota
from server.challenges.service import check_servable, lock_phase
from server.kit.errors import Conflict, Forbidden, Invalid, NotFound, Unavailable
from server.models import (
    FINAL_STATES,
    Challenge,
    EpisodeResultRow,
    Phase,
    State,
    Submission,
    TaskResultRow,
    Transition,
    User,
    team_id_of,
    utcnow,
)
from server.standings.entries import refresh
from server.submissions.changes import changed
from server.submissions.method import Method
from server.submissions.moderation import Moderation, flag_baseline, moderate
from server.submissions.states import queued_first, transition


@dataclass(frozen=True)
class Resolved:
    """What the image resolver returns: the reference to run, pinned, and its size."""

    pinned: str
    size_bytes: int | None


Resolver = Callable[[str], Resolved]


@dataclass(frozen=True)
class ImageGate:
    """A resolver that refuses container images while `refusal()` gives a reason (the
    embedded default without its engine or registry); bundled ``local:`` policies pass."""

    resolve_image: Resolver
    refusal: Callable[[], str | None]

    def __call__(self, image: str, *, owner: str | None = None) -> Resolved:
        if not image.startswith(LOCAL_PREFIX) and (reason := self.refusal()) is not None:
            raise Unavailable(reason, fields={"image": reason})
        if owner is None:
            return self.resolve_image(image)
        return resolve_as(self.resolve_image, image, owner=owner)


def resolve_as(resolve: Resolver, image: str, *, owner: str) -> Resolved:
    """Resolve for `owner` when the resolver checks whose image it is (the service's own
    registry: only one's own namespace), else as any resolver."""
    if "owner" in inspect.signature(resolve).parameters:
        resolved: Resolved = resolve(image, owner=owner)  # type: ignore[call-arg]
        return resolved
    return resolve(image)


def images_refused(resolve: Resolver) -> str | None:
    """Why this server takes no container images now, or None."""
    return resolve.refusal() if isinstance(resolve, ImageGate) else None


SHOWN_WITH = (
    joinedload(Submission.user),
    joinedload(Submission.challenge),
    joinedload(Submission.phase),
)
"""What a submission is shown with: its owner, challenge and phase (loaded in the same query)."""


def submit(
    db: DB,
    *,
    user: User,
    challenge: Challenge,
    phase: Phase,
    image: str,
    description: str,
    public: bool,
    resolve: Resolver,
    method: Method | None = None,
    require_verified_email: bool = False,
    policy_gpus: int = 0,
    now: datetime | None = None,
) -> Submission:
    """Accept a submission (state `queued`) or raise; the caller commits, then dispatches.
    `policy_gpus`: the GPUs this service can give a policy (`MANIEVAL_POLICY_GPUS`)."""
    stamped = now
    now = now or utcnow()
    if require_verified_email and user.email_verified_at is None:
        raise Forbidden(
            f"verify your email address before submitting: follow the link we sent to "
            f"{user.email}, or ask for a new one on your account page "
            "(or POST /api/v1/auth/verify/resend)"
        )
    if len(description) > 2000:
        raise Invalid("description too long", fields={"description": "at most 2000 characters"})
    named = (method or Method()).checked().stored()
    check_open(challenge, phase, now=now)
    check_servable(challenge, policy_gpus=policy_gpus)
    # Resolve before taking the lock: it talks to the registry.
    resolved = resolve_as(resolve, image, owner=user.username)

    # Locks the user (and their team): concurrent submissions cannot both pass the quota.
    team_id = check_quota(db, user=user, challenge=challenge, now=now)
    # Hold the phase's row (shared) and read its dates again, then the time: an organizer's
    # close (`close_phase`) is wholly before this submission or wholly after it.
    phase = lock_phase(db, phase_id=phase.id)
    now = stamped or utcnow()
    late = check_open(challenge, phase, now=now)

    submission = Submission(
        user=user,  # the objects, not only their ids: the answer shows them
        challenge=challenge,
        phase=phase,
        team_id=team_id,
        image=image,
        pinned_image=resolved.pinned,
        image_bytes=resolved.size_bytes,
        description=description,
        **named,
        public=public,
        state=State.QUEUED,
        reason="waiting for a worker",
        attempt=1,
        board_version=phase.pending_board_version or phase.board_version,
        post_deadline=late,
        created_at=now,
        updated_at=now,
    )
    db.add(submission)
    db.flush()
    queued_first(db, submission, "submitted", now=now)
    db.flush()
    return submission


def check_open(challenge: Challenge, phase: Phase, *, now: datetime) -> bool:
    """Conflict if the phase takes no submission now; True if it takes it for its
    post-deadline board, False for the official one."""
    if phase.is_open(now):
        return False
    if phase.has_opened(now) and phase.takes_late(now):
        return True
    early = not phase.has_opened(now)
    when = phase.opens_at if early else phase.closes_at
    verb = "opens" if early else "closed"
    raise Conflict(
        f"phase {phase.name!r} of {challenge.slug!r} {verb} at {when:%Y-%m-%d %H:%M} UTC",
        fields={"phase": f"not open for submissions ({verb})"},
    )


def visible_to(db: DB, submission: Submission, user: User | None) -> bool:
    """Whether `user` may see this submission at all (others get 404, not 403): its owner and
    admins always, anyone a public one, but on a board hidden until published only those who
    see its row (its team, in team mode): the one rule every route that shows it follows."""
    if user is not None and (user.is_admin or user.id == submission.user_id):
        return True
    if not submission.public or submission.hidden:
        return False
    phase = db.get(Phase, submission.phase_id)
    if phase is None or phase.board_shown_to_all():
        return True
    challenge = db.get(Challenge, submission.challenge_id)
    return (
        user is not None
        and challenge is not None
        and challenge.team_mode
        and submission.team_id is not None
        and submission.team_id == team_id_of(db, user_id=user.id)
    )


def owned_or_admin(submission: Submission, user: User | None) -> bool:
    """Whether `user` may see the private parts (episodes, log, videos) and act on it."""
    return user is not None and (user.is_admin or user.id == submission.user_id)


def find_visible(db: DB, *, submission_id: int, user: User | None) -> Submission | None:
    """The submission, with what it is shown with, if `user` may see it, else None."""
    submission = db.get(Submission, submission_id, options=SHOWN_WITH)
    if submission is None or not visible_to(db, submission, user):
        return None
    return submission


def get_visible(db: DB, *, submission_id: int, user: User | None) -> Submission:
    """The submission if `user` may see it, else NotFound (never Forbidden: no probing)."""
    submission = find_visible(db, submission_id=submission_id, user=user)
    if submission is None:
        raise NotFound(f"no submission {submission_id}")
    return submission


def get_owned(
    db: DB, *, submission_id: int, user: User | None, part: str | None = None
) -> Submission:
    """The submission, with what it is shown with, if `user` owns it or is an admin, else
    NotFound. With `part` (its owner-only part being asked for, "episodes"), a submission the
    user may see is Forbidden instead: it exists, and saying "no submission" would be a lie."""
    submission = db.get(Submission, submission_id, options=SHOWN_WITH)
    if submission is None or not owned_or_admin(submission, user):
        if part is not None and submission is not None and visible_to(db, submission, user):
            raise Forbidden(
                f"submission {submission_id} is public, but its {part} are visible to its "
                "owner only"
            )
        raise NotFound(f"no submission {submission_id}")
    return submission


def cancel(db: DB, user: User, submission: Submission, *, now: datetime | None = None) -> None:
    """Cancel by the owner (or an admin): the worker sees the state and stops the run."""
    if not owned_or_admin(submission, user):
        raise NotFound(f"no submission {submission.id}")
    if submission.state in FINAL_STATES:
        raise Conflict(f"submission {submission.id} already ended ({submission.state.value})")
    who = "an admin" if user.id != submission.user_id else "its owner"
    if not transition(
        db, submission.id, submission.attempt, State.CANCELLED, f"cancelled by {who}", now=now
    ):
        db.refresh(submission)
        raise Conflict(f"submission {submission.id} already ended ({submission.state.value})")
    db.refresh(submission)


def edit(
    db: DB,
    *,
    user: User,
    submission: Submission,
    public: bool | None = None,
    hidden: bool | None = None,
    baseline: bool | None = None,
    reason: str | None = None,
    description: str | None = None,
    method: Method | None = None,
) -> None:
    """The owner changes visibility, description and method; admins also hide (with a
    `reason`) and flag baselines, as organizer actions (`server.submissions.moderation`). The
    phase's leaderboard is recomputed for the submission's owner."""
    if not owned_or_admin(submission, user):
        raise NotFound(f"no submission {submission.id}")
    if (hidden is not None or baseline is not None) and not user.is_admin:
        raise Forbidden("only admins can hide submissions or flag baselines")
    changes: dict[str, bool | str | None] = {"public": public, "description": description}
    for name, value in changes.items():
        if value is not None:
            setattr(submission, name, value)
    for name, named in (method or Method()).checked().stored().items():
        setattr(submission, name, named)  # None here clears it
    db.flush()
    changed(db, submission.id)  # open views check again who may see it
    refresh(db, phase_id=submission.phase_id, user_id=submission.user_id)
    if baseline is not None:
        flag_baseline(db, by=user, submission=submission, baseline=baseline)
    if hidden or (hidden is False and submission.hidden):  # unhiding twice changes nothing
        action: Moderation = "hide" if hidden else "unhide"
        moderate(db, by=user, submission=submission, action=action, reason=reason)


# Reads ----------------------------------------------------------------------------------------


def list_submissions(
    db: DB,
    *,
    page: int,
    per_page: int,
    user: User | None = None,
    challenge: Challenge | None = None,
    phase: str | None = None,
    state: State | None = None,
) -> tuple[list[Submission], int]:
    """One page of submissions with what they are shown with, newest first (a user's, a
    challenge's, of phases of that name, in a state), and how many match."""
    query = select(Submission)
    if user is not None:
        query = query.where(Submission.user_id == user.id)
    if challenge is not None:
        query = query.where(Submission.challenge_id == challenge.id)
    if phase is not None:
        query = query.where(Submission.phase_id.in_(select(Phase.id).where(Phase.name == phase)))
    if state is not None:
        query = query.where(Submission.state == state)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.scalars(
        query.options(*SHOWN_WITH)
        .order_by(Submission.created_at.desc(), Submission.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    return list(rows), total


def transitions_of(db: DB, *, submission_id: int, after: int = 0) -> list[Transition]:
    """The submission's state changes after transition id `after`, in order."""
    return list(
        db.scalars(
            select(Transition)
            .where(Transition.submission_id == submission_id, Transition.id > after)
            .order_by(Transition.id)
        )
    )


@dataclass(frozen=True)
class TaskOutcome:
    """One task under one condition as pages, the API and the CLI show it. A rate and its
    interval are over the planned episodes: they are given only where every one of those ran,
    so that an evaluation that ended part-way shows what ran and invents nothing."""

    condition: str
    env_id: str
    episodes: int
    """Planned."""
    episodes_ran: int
    successes: int
    success_rate: float | None
    ci_low: float | None
    ci_high: float | None
    mean_steps: float | None
    """Over the episodes that ran; None when none did."""

    @property
    def complete(self) -> bool:
        return self.episodes_ran == self.episodes


def task_rows(db: DB, *, submission: Submission) -> list[TaskOutcome]:
    """The current attempt's per-task results, in the order the evaluator reported them."""
    rows = db.scalars(
        select(TaskResultRow)
        .where(
            TaskResultRow.submission_id == submission.id,
            TaskResultRow.attempt == submission.attempt,
        )
        .order_by(TaskResultRow.id)
    )
    return [task_outcome(row) for row in rows]


def task_outcome(row: TaskResultRow) -> TaskOutcome:
    """A stored task row as it is shown (a rate only where every planned episode ran)."""
    complete = row.episodes_ran == row.episodes
    return TaskOutcome(
        condition=row.condition,
        env_id=row.env_id,
        episodes=row.episodes,
        episodes_ran=row.episodes_ran,
        successes=row.successes,
        success_rate=row.success_rate if complete else None,
        ci_low=row.ci_low if complete else None,
        ci_high=row.ci_high if complete else None,
        mean_steps=row.mean_steps if row.episodes_ran else None,
    )


def provenance_of(submission: Submission) -> results.Provenance | None:
    """What produced the current attempt's result (None: no result, or one recorded before
    schema 1.2)."""
    found = (submission.result or {}).get("provenance")
    return results.Provenance.model_validate(found) if found else None


def condition_means(rows: list[TaskOutcome]) -> dict[str, float]:
    """Each condition's mean success rate over its tasks, for the conditions whose every
    planned episode ran."""
    partial = {row.condition for row in rows if not row.complete}
    return results.condition_means(
        (row.condition, row.success_rate or 0.0) for row in rows if row.condition not in partial
    )


def episode_rows(
    db: DB, *, submission: Submission, page: int, per_page: int
) -> tuple[list[tuple[EpisodeResultRow, str, str]], int]:
    """One page of the current attempt's episodes as (row, condition, task), and their total."""
    query = (
        select(EpisodeResultRow, TaskResultRow.condition, TaskResultRow.env_id)
        .join(TaskResultRow, EpisodeResultRow.task_result_id == TaskResultRow.id)
        .where(
            TaskResultRow.submission_id == submission.id,
            TaskResultRow.attempt == submission.attempt,
        )
    )
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.execute(
        query.order_by(TaskResultRow.id, EpisodeResultRow.index)
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    return [(row, condition, env_id) for row, condition, env_id in rows], total
