"""The stored rows of a leaderboard: recomputed for one (phase, user), or one (phase, team) in
team mode, whenever something that decides them changes (a result, a re-run, hiding,
visibility, the baseline flag, the method, a team's membership).

Who a row belongs to (docs/server.md, Teams):
- per-user mode (the default): a user's best public succeeded submission, whatever team they
  were in when they made it;
- team mode: a team's best submission made in the team (`Submission.team_id`, fixed when it was
  made), whoever of its members made it; a user not in a team has the row of their best
  submission made outside any team or in a dissolved one; a user in a team has no row of their
  own. A dissolved team has no row.
Baselines and disqualified submissions are always rows of their own, unranked. Each board
version of a phase (docs/server.md, Re-evaluation) has rows of its own, from the submissions
that count for it.

Locks: a refresh locks the user's row, then the rows of the teams they submitted in (id order),
then the phase's row. A caller that refreshes several users locks all of them first (id order),
then all of their teams (`server.teams.locks`).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import case, delete, or_, select, update
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import aliased

from evaluator.paired import Outcome, PackedOutcomes
from evaluator.provenance import recorded_environment
from evaluator.results import condition_means
from evaluator.stats import wilson_interval
from server.models import (
    Challenge,
    EpisodeResultRow,
    LeaderboardEntry,
    Phase,
    State,
    Submission,
    TaskResultRow,
    Team,
    User,
    team_id_of,
)


def standing(phase_id: int, board_version: int) -> tuple[Any, ...]:
    """Conditions on a submission that may stand on a board of this version of the phase, the
    official one or the post-deadline one: succeeded, scored, public and not hidden by the
    organizers (docs/server.md, Organizer tools)."""
    return (
        Submission.phase_id == phase_id,
        Submission.board_version == board_version,
        Submission.state == State.SUCCEEDED,
        Submission.public.is_(True),
        Submission.hidden.is_(False),
        Submission.score.is_not(None),
    )


def eligible_for(phase_id: int, board_version: int) -> tuple[Any, ...]:
    """Conditions on a submission that may stand on this version of the phase's official board
    (as a row or a record)."""
    return (
        *standing(phase_id, board_version),
        Submission.post_deadline.is_(False),  # the post-deadline board's, never the official
    )


def competing() -> tuple[Any, ...]:
    """Conditions on an eligible submission that competes for its participant's ranked row:
    neither a baseline nor disqualified (each of those is an unranked row of its own)."""
    return (Submission.baseline.is_(False), Submission.disqualified.is_(False))


def stands_alone(submission: Submission) -> bool:
    """Whether an eligible submission is an unranked row of its own (`competing`'s converse)."""
    return submission.baseline or submission.disqualified


_BEST = (Submission.score.desc(), Submission.created_at, Submission.id)
_LAST = (Submission.created_at.desc(), Submission.id.desc())
_MARKED = aliased(Submission)


def participant_of(submission: Submission, *, team_mode: bool) -> str:
    """Whose the submission is on a board, as a key: "team:ID" in team mode for one made in a
    team, else "user:ID" (a final mark is one per such key and phase)."""
    if team_mode and submission.team_id is not None:
        return f"team:{submission.team_id}"
    return f"user:{submission.user_id}"


def row_order(*, counts: str, final_choice: bool) -> tuple[Any, ...]:
    """The order of a participant's eligible submissions in a phase, their row first: their
    final choice (or its re-evaluation) where the phase has one, then the best or the latest
    (`counts`; docs/server.md, Challenge rules)."""
    rule = _LAST if counts == "last" else _BEST
    if not final_choice:
        return rule
    final = or_(
        Submission.final_for.is_not(None),
        Submission.reevaluation_of.in_(select(_MARKED.id).where(_MARKED.final_for.is_not(None))),
    )
    return (case((final, 0), else_=1), *rule)


def refresh(db: DB, *, phase_id: int, user_id: int) -> None:
    """Recompute a user's rows in a phase's leaderboard and, in team mode, the rows of the
    teams they submitted in (call inside the changing transaction)."""
    found = db.execute(
        select(Challenge.team_mode, Phase)
        .join(Phase, Phase.challenge_id == Challenge.id)
        .where(Phase.id == phase_id)
    ).first()
    if found is None:
        return
    team_mode, rules = bool(found[0]), found[1]
    order = row_order(counts=rules.counts, final_choice=rules.final_choice)
    # Serialise refreshes of one user (then of a team): the unique rows must not be raced.
    # Every writer locks a user before a team, and teams in id order.
    username = db.scalar(
        select(User.username).where(User.id == user_id).with_for_update(key_share=True)
    )
    if username is None:
        return
    # The user's rows go first and come back last: a submission just flagged a baseline may
    # still hold its team's row (the team's is recomputed in between), and one unflagged may
    # still hold a baseline row of the user's.
    _clear_user(db, phase_id=phase_id, user_id=user_id)
    if team_mode:
        teams = db.execute(
            select(Submission.team_id, Submission.board_version)
            .where(
                Submission.phase_id == phase_id,
                Submission.user_id == user_id,
                Submission.team_id.is_not(None),
            )
            .distinct()
        ).all()
        for team_id, version in sorted((t, v) for t, v in teams if t is not None):
            _refresh_team(
                db, phase_id=phase_id, team_id=team_id, board_version=version, order=order
            )
    versions = db.scalars(
        select(Submission.board_version)
        .where(Submission.phase_id == phase_id, Submission.user_id == user_id)
        .distinct()
    ).all()
    for version in sorted(versions):
        _fill_user(
            db,
            phase_id=phase_id,
            board_version=version,
            user_id=user_id,
            username=username,
            team_mode=team_mode,
            order=order,
        )
    moved(db, phase_id)
    db.flush()


def _clear_user(db: DB, *, phase_id: int, user_id: int) -> None:
    db.execute(
        delete(LeaderboardEntry).where(
            LeaderboardEntry.phase_id == phase_id,
            LeaderboardEntry.user_id == user_id,
            LeaderboardEntry.team_id.is_(None),
        )
    )


def _fill_user(
    db: DB,
    *,
    phase_id: int,
    board_version: int,
    user_id: int,
    username: str,
    team_mode: bool,
    order: tuple[Any, ...],
) -> None:
    eligible = db.scalars(
        select(Submission)
        .where(*eligible_for(phase_id, board_version), Submission.user_id == user_id)
        .order_by(*order)
    ).all()
    chosen = [s for s in eligible if stands_alone(s)]
    own = [s for s in eligible if not stands_alone(s)]
    if team_mode:
        in_team = team_id_of(db, user_id=user_id)
        gone = _dissolved(db, team_ids={s.team_id for s in own if s.team_id is not None})
        own = [] if in_team is not None else [s for s in own if s.team_id in gone | {None}]
    chosen += own[:1]
    for submission in chosen:
        key = None if stands_alone(submission) else user_id
        db.add(_entry(db, submission, username=username, owner_key=key, team=None))


def _dissolved(db: DB, *, team_ids: set[int]) -> set[int | None]:
    if not team_ids:
        return set()
    found = db.scalars(
        select(Team.id).where(Team.id.in_(team_ids), Team.dissolved_at.is_not(None))
    ).all()
    return set(found)


def _refresh_team(
    db: DB, *, phase_id: int, team_id: int, board_version: int, order: tuple[Any, ...]
) -> None:
    team = db.scalar(select(Team).where(Team.id == team_id).with_for_update(key_share=True))
    db.execute(
        delete(LeaderboardEntry).where(
            LeaderboardEntry.phase_id == phase_id,
            LeaderboardEntry.board_version == board_version,
            LeaderboardEntry.team_id == team_id,
        )
    )
    if team is None or team.dissolved_at is not None:
        return
    best = db.execute(
        select(Submission, User.username)
        .join(User, User.id == Submission.user_id)
        .where(
            *eligible_for(phase_id, board_version),
            Submission.team_id == team_id,
            *competing(),
        )
        .order_by(*order)
        .limit(1)
    ).first()
    if best is not None:
        db.add(_entry(db, best[0], username=best[1], owner_key=None, team=team))


def _entry(
    db: DB, submission: Submission, *, username: str, owner_key: int | None, team: Team | None
) -> LeaderboardEntry:
    assert submission.score is not None
    return LeaderboardEntry(
        phase_id=submission.phase_id,
        board_version=submission.board_version,
        submission_id=submission.id,
        user_id=submission.user_id,
        owner_key=owner_key,
        team_id=team.id if team is not None else None,
        team_name=team.name if team is not None else None,
        team_display_name=team.display_name if team is not None else None,
        baseline=submission.baseline,
        score=submission.score,
        submitted_at=submission.created_at,
        username=username,
        method=submission.method,
        paper_url=submission.paper_url,
        code_url=submission.code_url,
        summary=summary(db, submission=submission),
        outcomes=packed_outcomes(db, submission=submission),
    )


def refresh_member(db: DB, *, user_id: int) -> None:
    """Recompute every team-mode board the user has submitted to: their team changed."""
    phases = db.scalars(
        select(Submission.phase_id)
        .join(Challenge, Challenge.id == Submission.challenge_id)
        .where(Submission.user_id == user_id, Challenge.team_mode.is_(True))
        .distinct()
    ).all()
    for phase_id in sorted(phases):
        refresh(db, phase_id=phase_id, user_id=user_id)


def release_team(db: DB, *, team_id: int) -> None:
    """After a team is dissolved (its row kept and marked, its submissions untouched): its rows
    go, and its submitters' rows are recomputed, where those submissions are their own now.
    The caller holds the submitters' rows, then their teams' (the module's lock order)."""
    made = db.execute(
        select(Submission.phase_id, Submission.user_id).where(Submission.team_id == team_id)
    ).all()
    db.execute(delete(LeaderboardEntry).where(LeaderboardEntry.team_id == team_id))
    for phase_id, user_id in sorted(set(made)):
        refresh(db, phase_id=phase_id, user_id=user_id)


def rebuild(db: DB, *, challenge_id: int) -> None:
    """Recompute every board of a challenge (its team mode changed)."""
    phases = db.scalars(select(Phase.id).where(Phase.challenge_id == challenge_id)).all()
    for phase_id in phases:
        db.execute(delete(LeaderboardEntry).where(LeaderboardEntry.phase_id == phase_id))
        users = db.scalars(
            select(Submission.user_id).where(Submission.phase_id == phase_id).distinct()
        ).all()
        for user_id in sorted(users):
            refresh(db, phase_id=phase_id, user_id=user_id)
        moved(db, phase_id)
    db.flush()


def summary(db: DB, *, submission: Submission) -> dict[str, Any]:
    """Per-condition scores and per-task success with intervals, for the leaderboard row."""
    rows = db.scalars(
        select(TaskResultRow)
        .where(
            TaskResultRow.submission_id == submission.id,
            TaskResultRow.attempt == submission.attempt,
        )
        .order_by(TaskResultRow.id)
    ).all()
    tasks: dict[str, dict[str, float]] = {}
    first: str | None = None
    successes = episodes = 0
    for row in rows:
        first = first or row.condition
        if row.condition == first:
            tasks[row.env_id] = {
                "success_rate": row.success_rate,
                "ci_low": row.ci_low,
                "ci_high": row.ci_high,
            }
            successes += row.successes
            episodes += row.episodes
    disqualified = {"disqualified": submission.moderation_reason or ""}
    return {
        **(disqualified if submission.disqualified else {}),
        "conditions": condition_means((row.condition, row.success_rate) for row in rows),
        "tasks": tasks,
        # The score's 95% interval: Wilson over the first condition's episodes pooled.
        "score_interval": list(wilson_interval(successes, episodes)) if rows else None,
        # Compared with the service's current one when the board is read (docs/metrics.md).
        "environment": recorded_environment(submission.result or {}),
    }


def ranked_outcomes(db: DB, *, submission: Submission) -> tuple[str, list[Outcome]] | None:
    """The ranked (first) condition's name and its episodes' outcomes, from the current
    attempt's episode rows; None when it has none."""
    rows = db.execute(
        select(
            TaskResultRow.condition,
            TaskResultRow.env_id,
            EpisodeResultRow.index,
            EpisodeResultRow.seed,
            EpisodeResultRow.success_once,
        )
        .join(TaskResultRow, EpisodeResultRow.task_result_id == TaskResultRow.id)
        .where(
            TaskResultRow.submission_id == submission.id,
            TaskResultRow.attempt == submission.attempt,
        )
        .order_by(TaskResultRow.id, EpisodeResultRow.index)
    ).all()
    if not rows:
        return None
    first = rows[0].condition  # the first task row's, as in `summary`
    return first, [Outcome(*row) for row in rows if row.condition == first]


def packed_outcomes(db: DB, *, submission: Submission) -> dict[str, Any] | None:
    """What a board row keeps of its episodes for the tie groups (`LeaderboardEntry.outcomes`)."""
    found = ranked_outcomes(db, submission=submission)
    if found is None:
        return None
    condition, outcomes = found
    return PackedOutcomes.of(outcomes, condition=condition).as_json()


def moved(db: DB, phase_id: int) -> None:
    """The phase's board changed: readers keyed on its version read it again."""
    db.execute(
        update(Phase)
        .where(Phase.id == phase_id)
        .values(leaderboard_version=Phase.leaderboard_version + 1)
    )
