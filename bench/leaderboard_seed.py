"""Seed data for bench/leaderboard_load.py: users, submissions, per-task results and the
leaderboard rows they imply, written with COPY; and a check that those rows are what
``server.leaderboard.service.refresh`` writes.

Episode rows and result documents are left out: the leaderboard reads neither.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
from sqlalchemy import Engine, select, text
from sqlalchemy.orm import Session

from evaluator.stats import wilson_interval
from server.kit.security import hash_password
from server.models import LeaderboardEntry, State
from server.standings.entries import refresh

EPISODES = 50
BASELINES_PER_PHASE = 3
ADMIN_ID = 1  # owns the baselines
DEV_SHARE = 0.75  # of submissions in the dev phase; the rest go to test
RERUN_SHARE = 0.03  # of succeeded submissions re-run once: attempt 1's rows stay behind
STATES = {
    State.SUCCEEDED: 0.85,
    State.FAILED: 0.06,
    State.ERROR: 0.03,
    State.CANCELLED: 0.02,
    State.TIMED_OUT: 0.01,
    State.QUEUED: 0.02,
    State.RUNNING: 0.01,
}
REASONS = {
    State.FAILED: "the policy exited with status 1",
    State.ERROR: "the evaluation pod was evicted",
    State.CANCELLED: "cancelled by the owner",
    State.TIMED_OUT: "the evaluation exceeded its budget of 7200 s",
}
WILSON = [wilson_interval(k, EPISODES) for k in range(EPISODES + 1)]


@dataclass(frozen=True)
class Layout:
    """What the challenge looks like: its id, phase ids by name, tasks and conditions."""

    challenge_id: int
    phases: dict[str, int]
    tasks: list[str]
    conditions: list[str]


@dataclass
class Submissions:
    """Column arrays of the generated submissions (index i is submission id i + 1)."""

    user: np.ndarray
    phase: np.ndarray
    state: list[State]
    created: list[datetime]
    public: np.ndarray
    hidden: np.ndarray
    baseline: np.ndarray
    attempt: np.ndarray
    successes: dict[int, np.ndarray]  # (attempt, condition, task) counts, succeeded ones only
    score: dict[int, float]


def generate(layout: Layout, users: int, count: int, seed: int) -> Submissions:
    """Submissions skewed over users (a few very active), each user with a skill level."""
    rng = np.random.default_rng(seed)
    activity = rng.lognormal(0.0, 1.0, users)
    user = rng.choice(users, size=count, p=activity / activity.sum()) + 1
    phase_ids = np.array([layout.phases["dev"], layout.phases["test"]])
    phase = phase_ids[(rng.random(count) > DEV_SHARE).astype(int)]
    states = list(STATES)
    state = [states[i] for i in rng.choice(len(states), size=count, p=list(STATES.values()))]
    baseline = np.zeros(count, dtype=bool)
    public, hidden = rng.random(count) > 0.05, rng.random(count) < 0.01
    for k, phase_id in enumerate(phase_ids):  # the first submissions are the baselines
        rows = slice(k * BASELINES_PER_PHASE, (k + 1) * BASELINES_PER_PHASE)
        user[rows], phase[rows], baseline[rows] = ADMIN_ID, phase_id, True
        public[rows], hidden[rows] = True, False
        for i in range(rows.start, rows.stop):
            state[i] = State.SUCCEEDED
    start = datetime.now(UTC) - timedelta(days=120)
    offsets = np.sort(rng.uniform(0, 120 * 86400, count))
    created = [start + timedelta(seconds=float(s)) for s in offsets]
    skill = rng.beta(2.0, 4.0, users + 1)
    difficulty = np.linspace(1.0, 0.3, len(layout.tasks))
    harshness = np.linspace(1.0, 0.5, len(layout.conditions))
    succeeded = [i for i, s in enumerate(state) if s == State.SUCCEEDED]
    reruns = set(rng.choice(succeeded, size=int(len(succeeded) * RERUN_SHARE), replace=False))
    attempt = np.ones(count, dtype=int)
    attempt[list(reruns)] = 2
    # Two attempts' worth for everyone; a submission keeps as many as it had.
    mean = skill[user[succeeded]][:, None, None, None] * np.outer(harshness, difficulty)
    noise = rng.normal(0.0, 0.05, (len(succeeded), 2, *mean.shape[2:]))
    counts = rng.binomial(EPISODES, np.clip(mean + noise, 0.0, 1.0))
    successes = {i: counts[k, : attempt[i]] for k, i in enumerate(succeeded)}
    score: dict[int, float] = {}
    for i, drawn in successes.items():
        rates = [k / EPISODES for k in drawn[-1, 0].tolist()]
        score[i] = sum(rates) / len(rates)
    return Submissions(
        user=user,
        phase=phase,
        state=state,
        created=created,
        public=public,
        hidden=hidden,
        baseline=baseline,
        attempt=attempt,
        successes=successes,
        score=score,
    )


def user_rows(users: int, now: datetime) -> Iterator[tuple[Any, ...]]:
    password = hash_password("bench-password")  # once: argon2 is slow on purpose
    for uid in range(1, users + 1):
        name = "bench-admin" if uid == ADMIN_ID else f"user{uid:05d}"
        created = now - timedelta(days=150, seconds=uid)
        yield uid, name, f"{name}@bench.invalid", password, uid == ADMIN_ID, created


def submission_rows(layout: Layout, subs: Submissions) -> Iterator[tuple[Any, ...]]:
    for i, state in enumerate(subs.state):
        created = subs.created[i]
        started = None if state == State.QUEUED else created + timedelta(seconds=30)
        finished = created + timedelta(minutes=40) if state.final else None
        image = f"127.0.0.1:5000/user{int(subs.user[i])}/policy:v{i % 7}"
        yield (
            i + 1,
            int(subs.user[i]),
            layout.challenge_id,
            int(subs.phase[i]),
            image,
            image.rsplit(":", 1)[0] + "@sha256:" + f"{i:064x}",
            250_000_000 + i,
            "",
            bool(subs.public[i]),
            bool(subs.hidden[i]),
            bool(subs.baseline[i]),
            state.value,
            REASONS.get(state, ""),
            int(subs.attempt[i]),
            created,
            finished or started or created,
            started,
            finished,
            subs.score.get(i),
            "",
        )


def task_rows(layout: Layout, subs: Submissions) -> Iterator[tuple[Any, ...]]:
    """Rows in the order ingest stores them: attempt, then condition, then task."""
    row_id = 0
    for i, counts in subs.successes.items():
        for a, per_condition in enumerate(counts.tolist(), start=1):
            for condition, per_task in zip(layout.conditions, per_condition, strict=True):
                for env_id, k in zip(layout.tasks, per_task, strict=True):
                    row_id += 1
                    low, high = WILSON[k]
                    steps = 100.0 - 60.0 * k / EPISODES
                    rate = k / EPISODES
                    yield row_id, i + 1, a, condition, env_id, EPISODES, k, rate, low, high, steps


def summary(layout: Layout, counts: np.ndarray) -> dict[str, Any]:
    """The current attempt's summary, computed as server.leaderboard.service.summary does."""
    rates = [[k / EPISODES for k in per_task] for per_task in counts[-1].tolist()]
    tasks = {
        env_id: {"success_rate": rate, "ci_low": WILSON[k][0], "ci_high": WILSON[k][1]}
        for env_id, rate, k in zip(layout.tasks, rates[0], counts[-1, 0].tolist(), strict=True)
    }
    conditions = {c: sum(r) / len(r) for c, r in zip(layout.conditions, rates, strict=True)}
    first = counts[-1, 0].tolist()  # the score's interval: Wilson over the first condition's
    pooled = wilson_interval(sum(first), EPISODES * len(first))  # episodes, pooled
    return {"conditions": conditions, "tasks": tasks, "score_interval": list(pooled)}


def entry_rows(layout: Layout, subs: Submissions) -> Iterator[tuple[Any, ...]]:
    """Per (phase, user): the best eligible regular submission and every eligible baseline."""
    eligible: dict[tuple[int, int], list[int]] = {}
    for i in subs.successes:
        if subs.public[i] and not subs.hidden[i]:
            eligible.setdefault((int(subs.phase[i]), int(subs.user[i])), []).append(i)
    entry_id = 0
    for (phase_id, uid), found in sorted(eligible.items()):
        found.sort(key=lambda i: (-subs.score[i], subs.created[i], i))
        chosen = [i for i in found if subs.baseline[i]]
        chosen += [i for i in found if not subs.baseline[i]][:1]
        name = "bench-admin" if uid == ADMIN_ID else f"user{uid:05d}"
        for i in chosen:
            entry_id += 1
            owner = None if subs.baseline[i] else uid
            data = json.dumps(summary(layout, subs.successes[i]))
            baseline, score = bool(subs.baseline[i]), subs.score[i]
            yield (
                entry_id,
                phase_id,
                i + 1,
                uid,
                owner,
                baseline,
                score,
                subs.created[i],
                name,
                data,
            )


COLUMNS = {
    "users": "id, username, email, password_hash, is_admin, created_at",
    "submissions": "id, user_id, challenge_id, phase_id, image, pinned_image, image_bytes, "
    "description, public, hidden, baseline, state, reason, attempt, created_at, updated_at, "
    "started_at, finished_at, score, log_tail",
    "task_results": "id, submission_id, attempt, condition, env_id, episodes, successes, "
    "success_rate, ci_low, ci_high, mean_steps",
    "leaderboard_entries": "id, phase_id, submission_id, user_id, owner_key, baseline, score, "
    "submitted_at, username, summary",
}


def seed(
    engine: Engine, layout: Layout, *, users: int, submissions: int
) -> tuple[dict[str, float], dict[str, int]]:
    """Write everything; returns seconds per step and rows per table, for the report."""
    took: dict[str, float] = {}
    rows_in: dict[str, int] = {}
    t0 = time.perf_counter()
    subs = generate(layout, users, submissions, seed=20240601)
    took["generate"] = time.perf_counter() - t0
    now = datetime.now(UTC)
    sources = {
        "users": user_rows(users, now),
        "submissions": submission_rows(layout, subs),
        "task_results": task_rows(layout, subs),
        "leaderboard_entries": entry_rows(layout, subs),
    }
    with engine.begin() as conn:
        # Skips the per-row foreign-key triggers, which halve the load speed (rows are
        # consistent by construction and verify() checks a sample); needs a superuser.
        conn.execute(text("SET LOCAL session_replication_role = replica"))
        cursor = conn.connection.driver_connection.cursor()  # type: ignore[union-attr]
        for table, rows in sources.items():
            t0 = time.perf_counter()
            n = 0
            with cursor.copy(f"COPY {table} ({COLUMNS[table]}) FROM STDIN") as copy:
                for row in rows:
                    copy.write_row(row)
                    n += 1
            took[table] = time.perf_counter() - t0
            rows_in[table] = n
            conn.execute(
                text(f"SELECT setval(pg_get_serial_sequence('{table}', 'id'), {max(n, 1)})")
            )
        conn.execute(text("UPDATE phases SET leaderboard_version = :v"), {"v": len(subs.successes)})
    t0 = time.perf_counter()
    with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
        conn.execute(text("VACUUM ANALYZE"))
    took["vacuum analyze"] = time.perf_counter() - t0
    return took, rows_in


VERIFY_SAMPLES = {
    "with a row": "SELECT phase_id, user_id FROM leaderboard_entries WHERE NOT baseline",
    "with a re-run": "SELECT phase_id, user_id FROM submissions WHERE attempt = 2 "
    "AND state = 'succeeded'",
    "with a private or hidden one": "SELECT phase_id, user_id FROM submissions "
    "WHERE state = 'succeeded' AND (NOT public OR hidden)",
    "with baselines": "SELECT phase_id, user_id FROM submissions WHERE baseline",
}


def verify(engine: Engine, sample: int) -> tuple[dict[str, int], float]:
    """Run refresh() on sampled (phase, user) pairs of each kind and compare its rows with the
    seeded ones (rolled back afterwards). Returns pairs per kind and ms per refresh()."""
    spent, calls = 0.0, 0
    checked: dict[str, int] = {}
    with Session(engine) as db:
        for kind, query in VERIFY_SAMPLES.items():
            pairs = db.execute(text(f"SELECT DISTINCT * FROM ({query}) q ORDER BY 1, 2")).all()
            pairs = pairs[:: max(1, len(pairs) // sample)][:sample]
            for phase_id, user_id in pairs:
                before = _entries(db, phase_id, user_id)
                t0 = time.perf_counter()
                refresh(db, phase_id=phase_id, user_id=user_id)
                spent, calls = spent + time.perf_counter() - t0, calls + 1
                after = _entries(db, phase_id, user_id)
                if before != after:
                    raise AssertionError(f"phase {phase_id} user {user_id}: {before} != {after}")
            checked[kind] = len(pairs)
        db.rollback()
    return checked, spent / max(calls, 1) * 1000


def _entries(db: Session, phase_id: int, user_id: int) -> list[tuple[Any, ...]]:
    e = LeaderboardEntry
    query = (
        select(e.submission_id, e.owner_key, e.baseline, e.score, e.submitted_at)
        .add_columns(e.username, e.summary)
        .where(e.phase_id == phase_id, e.user_id == user_id)
        .order_by(e.submission_id)
    )
    return [tuple(row) for row in db.execute(query)]
