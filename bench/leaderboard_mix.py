"""The honest load of bench/leaderboard_load.py: what readers ask for, and writes meanwhile.

Reads: every page of both phases at several page sizes as JSON, as CSV at two, and the web
page sorted by each kind of column in both directions (its first pages), shuffled, so that a
cache holds only what it earns. Writes: seeded queued and running submissions finish at a
steady rate while the load runs, reported as a worker reports them (`report_state`,
`report_final`): each one refreshes its owner's leaderboard row and moves the board on.
"""

from __future__ import annotations

import random
import threading
import time
from datetime import UTC, datetime

from sqlalchemy import Engine, select, text
from sqlalchemy.orm import Session

from evaluator.results import (
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    SuiteRef,
    Versions,
    aggregate_task,
)
from server.kit.db import make_engine
from server.models import State, Submission
from server.submissions.reports import report_final, report_state

JSON_PAGE_SIZES = (10, 25, 50, 100)
CSV_PAGE_SIZES = (50, 100)
WEB_PAGES = 3
EPISODES = 5


def mixed_paths(engine: Engine, *, slug: str, tasks: list[str], stresses: list[str]) -> list[str]:
    """Every page of both phases (JSON at every size, CSV at two), the web page's first pages
    under every sort key kind in both directions; shuffled with a fixed seed."""
    with engine.connect() as conn:
        rows = dict(
            conn.execute(
                text(
                    "SELECT p.name, count(e.id) FROM phases p "
                    "LEFT JOIN leaderboard_entries e ON e.phase_id = p.id GROUP BY p.name"
                )
            ).all()
        )
    api = f"/api/v1/challenges/{slug}/leaderboard"
    paths = []
    for phase, count in rows.items():
        for size in JSON_PAGE_SIZES:
            pages = max(1, -(-count // size))
            paths += [f"{api}?phase={phase}&page={p}&per_page={size}" for p in range(1, pages + 1)]
        for size in CSV_PAGE_SIZES:
            pages = max(1, -(-count // size))
            paths += [
                f"{api}?phase={phase}&page={p}&per_page={size}&format=csv"
                for p in range(1, pages + 1)
            ]
        sorts = ["rank", "user", "score", "submitted", f"task:{tasks[0]}", f"cond:{stresses[0]}"]
        paths += [
            f"/challenges/{slug}/leaderboard?phase={phase}&sort={sort}&dir={way}&page={p}"
            for sort in sorts
            for way in ("asc", "desc")
            for p in range(1, WEB_PAGES + 1)
        ]
    random.Random(7).shuffle(paths)
    return paths


def result_for(
    rng: random.Random, *, phase: str, suite: SuiteRef, tasks: list[str], conditions: list[str]
) -> EvaluationResult:
    """A completed core-suite result with random outcomes."""
    condition_results = []
    for name in conditions:
        task_results = []
        for env_id in tasks:
            episodes = [
                EpisodeResult(
                    index=i,
                    seed=i,
                    success_once=rng.random() < 0.5,
                    success_at_end=None,
                    steps=50,
                    episode_return=1.0,
                    wall_time_s=1.0,
                )
                for i in range(EPISODES)
            ]
            task_results.append(aggregate_task(env_id, EPISODES, episodes))
        score = sum(t.success_rate for t in task_results) / len(task_results)
        condition_results.append(
            ConditionResult(name=name, params={"kind": name}, score=score, tasks=task_results)
        )
    now = datetime.now(UTC)
    return EvaluationResult(
        suite=suite,
        phase=phase,
        policy="bench",
        versions=Versions(manieval="0", mani_skill="0", sapien="0", torch="0", python="3"),
        started_at=now,
        finished_at=now,
        status="completed",
        score=condition_results[0].score,
        conditions=condition_results,
    )


class Finisher(threading.Thread):
    """Finishes seeded queued and running submissions, `per_second` of them, until stopped."""

    def __init__(
        self, url: str, *, per_second: float, suite: SuiteRef, tasks: list[str], stresses: list[str]
    ) -> None:
        super().__init__(name="bench-finisher", daemon=True)
        self._engine = make_engine(url)
        self._per_second = per_second
        self._suite = suite
        self._tasks = tasks
        self._conditions = ["nominal", *stresses]
        self._halt = threading.Event()
        self._rng = random.Random(11)
        with Session(self._engine) as db:
            waiting = db.execute(
                select(Submission.id, Submission.state, Submission.attempt).where(
                    Submission.state.in_((State.QUEUED, State.RUNNING))
                )
            ).all()
        self._waiting = [tuple(row) for row in waiting]
        self._rng.shuffle(self._waiting)
        self.finished = 0
        self.failed: list[str] = []

    def run(self) -> None:
        started = time.monotonic()
        while not self._halt.is_set() and self._waiting:
            due = started + self.finished / self._per_second
            if self._halt.wait(max(0.0, due - time.monotonic())):
                break
            sid, state, attempt = self._waiting.pop()
            try:
                self._finish(sid, state, attempt)
                self.finished += 1
            except Exception as exc:  # reported, not fatal: the load goes on
                self.failed.append(f"{sid}: {type(exc).__name__}: {exc}")

    def _finish(self, sid: int, state: State, attempt: int) -> None:
        with Session(self._engine) as db:
            phase = db.scalar(
                text(
                    "SELECT p.name FROM submissions s JOIN phases p ON p.id = s.phase_id "
                    "WHERE s.id = :s"
                ),
                {"s": sid},
            )
            if state == State.QUEUED:
                report_state(db, sid, attempt, State.LAUNCHING, "starting")
                report_state(db, sid, attempt, State.RUNNING, "evaluating")
            doc = result_for(
                self._rng,
                phase=str(phase),
                suite=self._suite,
                tasks=self._tasks,
                conditions=self._conditions,
            )
            report_final(db, sid, attempt, State.SUCCEEDED, "done", result=doc)
            db.commit()

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=30)
        self._engine.dispose()
