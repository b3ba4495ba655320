"""A challenge's page: rules, phases, quota, seed commitments, the top of the leaderboard and
the best score over time. It shows the challenge's board, so it lives with the leaderboard's
pages, above the challenges (whose home page lists them, server/challenges/pages.py)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.accounts.deps import ViewerDep
from server.challenges.charts import StepChart, best_over_time, step_chart
from server.challenges.prose import markdown, markdown_inline
from server.challenges.quota import quota_use
from server.challenges.service import get_challenge, shown_phase, suite_of
from server.challenges.tracks import track_name, tracks_of
from server.challenges.verification import stored_verification
from server.kit.deps import DBDep
from server.kit.pages import render
from server.leaderboard.columns import Column, board_columns
from server.leaderboard.pages import top_rows
from server.leaderboard.service import Board, baseline_points, record_points
from server.models import Challenge, Phase, User, utcnow

router = APIRouter(include_in_schema=False)


@dataclass(frozen=True)
class TrackBoard:
    """The top of another track's board in the same phase, shown on the challenge's page."""

    name: str
    challenge: Challenge
    phase: Phase
    board: Board
    tasks: list[str]
    columns: list[Column]


def track_boards(
    request: Request, db: DB, challenge: Challenge, *, phase: str, viewer: User | None
) -> list[TrackBoard]:
    """The top rows of every other track of the challenge's group, each in the phase of the
    same name (else the phase its page would show): a challenge with tracks shows each board."""
    shown = []
    for track in tracks_of(db, challenge):
        if track.id == challenge.id:
            continue
        named = next((p for p in track.phases if p.name == phase), None)
        track_phase = named or shown_phase(track, name=None)
        tasks = [t.env_id for t in suite_of(track).tasks]
        board = top_rows(
            request, db, slug=track.slug, phase=track_phase.name, count=TOP_ROWS, viewer=viewer
        )
        shown.append(
            TrackBoard(
                name=track_name(track),
                challenge=track,
                phase=track_phase,
                board=board,
                tasks=tasks,
                columns=board_columns(tasks, []),
            )
        )
    return shown


TOP_ROWS = 10  # rows of the board shown on the challenge page
PhaseName = Annotated[str | None, Query(max_length=32)]


@router.get("/challenges/{slug}")
def challenge_page(
    slug: str, request: Request, who: ViewerDep, db: DBDep, phase: PhaseName = None
) -> Response:
    """Description, tasks, rules, phases, quota, seed commitments, leaderboard, history and
    the suite's verification."""
    challenge = get_challenge(db, slug=slug)
    shown = shown_phase(challenge, name=phase)
    now = utcnow()
    quota = (
        quota_use(db, user=who.user, challenge=challenge, now=now) if who.user is not None else None
    )
    board = top_rows(
        request, db, slug=challenge.slug, phase=shown.name, count=TOP_ROWS, viewer=who.user
    )
    organizer = who.user is not None and who.user.is_admin
    hidden = not shown.board_shown_to_all() and not organizer  # its history would tell
    suite = suite_of(challenge)
    return render(
        request,
        who,
        "challenge.html",
        challenge=challenge,
        description=markdown(challenge.description),
        phase_notes={name: markdown_inline(p.description) for name, p in suite.phases.items()},
        suite=suite,
        tasks=[t.env_id for t in suite.tasks],
        columns=board_columns([t.env_id for t in suite.tasks], []),
        phase=shown,
        now=now,
        quota=quota,
        board=board,
        chart=None if hidden else request.app.state.score_history.chart(db, shown),
        verification=stored_verification(challenge.verification),
        track=track_name(challenge),
        tracks=tracks_of(db, challenge),
        track_boards=track_boards(request, db, challenge, phase=shown.name, viewer=who.user),
    )


class ScoreHistory:
    """Best-score-over-time charts per (phase, board version): the version changes whenever
    something that decides the board does, so a cached chart is never stale."""

    def __init__(self, size: int = 64) -> None:
        self._charts: OrderedDict[tuple[int, int], StepChart | None] = OrderedDict()
        self._size = size
        self._lock = threading.Lock()

    def chart(self, db: DB, phase: Phase, *, now: Callable[[], Any] = utcnow) -> StepChart | None:
        key = (phase.id, phase.leaderboard_version)
        with self._lock:
            if key in self._charts:
                self._charts.move_to_end(key)
                return self._charts[key]
        drawn = step_chart(
            best_over_time(record_points(db, phase_id=phase.id)),
            now=now(),
            baselines=baseline_points(db, phase_id=phase.id),
        )
        with self._lock:
            self._charts[key] = drawn
            while len(self._charts) > self._size:
                self._charts.popitem(last=False)
        return drawn
