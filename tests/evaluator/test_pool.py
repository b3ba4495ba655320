"""Warm evaluator processes: kept between evaluations, the same records as in-process runs, a
crash or a cancel never hands a broken pool to the next evaluation."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil
import pytest

from evaluator import evaluation
from evaluator import pool as pools
from evaluator.evaluation import evaluate
from evaluator.pool import EvaluatorCrashed, WarmPool, leased
from evaluator.results import EpisodeResult, episode_records
from evaluator.runner import RunOptions, make_shards
from evaluator.sources import LocalDirectory

from .conftest import HERE, RANDOM, REPO, SCRIPTED, tiny_plan


@dataclass(frozen=True)
class Crashing:
    """A policy source whose launch ends the evaluator process it runs in, as a simulator crash
    would: the evaluation must end as the platform's failure."""

    def describe(self) -> str:
        return "crashing"

    def pinned_image(self) -> None:
        return None

    def launch(self, *, endpoint: str, socket_dir: Path) -> Any:
        os._exit(3)


def test_a_leased_pool_is_kept_and_gives_the_in_process_records() -> None:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal", "obs_noise"])
    here = evaluate(plan, LocalDirectory(SCRIPTED))
    shards = make_shards(plan, 2)
    with leased(2) as pool:
        first = pool.run(plan, LocalDirectory(SCRIPTED), shards, RunOptions(), _ignore, _never)
    with leased(2) as again:  # the same processes, already warm
        assert again is pool
        second = again.run(plan, LocalDirectory(SCRIPTED), shards, RunOptions(), _ignore, _never)
    for outcomes in (first, second):
        assert sorted((r, e.index) for o in outcomes for r, e in o.episodes) == [
            (r, i) for r in range(2) for i in range(3)
        ]
    warm = evaluate(plan, LocalDirectory(SCRIPTED), workers=2, warm=True)
    assert episode_records(warm) == episode_records(here)


def test_a_warm_run_of_one_worker_runs_outside_this_process(monkeypatch: Any) -> None:
    plan = tiny_plan(tasks=["PushCube-v1"], conditions=["nominal"])
    here = evaluate(plan, LocalDirectory(SCRIPTED))

    def not_here(*_args: Any, **_kwargs: Any) -> None:
        raise AssertionError("a warm run ran its shard in the lessee's process")

    monkeypatch.setattr(evaluation, "run_shard", not_here)  # the evaluator processes keep theirs
    seen: list[EpisodeResult] = []
    warm = evaluate(
        plan,
        LocalDirectory(SCRIPTED),
        warm=True,
        on_episode=lambda _run, episode: seen.append(episode),
    )
    assert episode_records(warm) == episode_records(here)
    assert [e.index for e in seen] == [0, 1, 2]  # reported live, across the process boundary
    assert idle_pools() >= 1


def test_a_crashed_evaluator_process_fails_the_evaluation_and_its_pool_is_not_reused() -> None:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"])
    with pytest.raises(EvaluatorCrashed, match="evaluator process ended"):
        with leased(1) as broken:
            broken.run(plan, Crashing(), make_shards(plan, 1), RunOptions(), _ignore, _never)
    assert not broken.usable
    with leased(1) as fresh:
        assert fresh is not broken
        outcomes = fresh.run(
            plan, LocalDirectory(SCRIPTED), make_shards(plan, 1), RunOptions(), _ignore, _never
        )
    assert [e.failure for _, e in outcomes[0].episodes] == [None, None, None]


def test_a_pool_that_lost_a_process_while_idle_is_replaced() -> None:
    """An idle pool whose process died (the OOM killer, say) is not the evaluation's fault: it
    runs whole on a new pool."""
    with leased(1) as pool:
        pool.warm()
    executor = pool._executor
    victim = next(iter(executor._processes.values()))  # type: ignore[attr-defined]
    victim.kill()
    victim.join(timeout=60)
    deadline = time.monotonic() + 120
    while not executor._broken:  # type: ignore[attr-defined]  # the executor notices on its own
        assert time.monotonic() < deadline, "the executor never noticed its dead process"
        time.sleep(0.1)
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"])
    result = evaluate(plan, LocalDirectory(SCRIPTED), warm=True)
    assert [e.failure for e in result.conditions[0].tasks[0].episodes] == [None, None, None]
    with leased(1) as again:
        assert again is not pool


def test_a_pool_left_idle_for_its_lifetime_ends_its_processes(monkeypatch: Any) -> None:
    monkeypatch.setattr(pools, "IDLE_LIFETIME_S", 0.5)
    with leased(3) as pool:  # a size of its own: no other test's idle pool is leased here
        pool.warm()
        processes = [psutil.Process(p.pid) for p in pool._executor._processes.values()]  # type: ignore[attr-defined]
    assert len(processes) == 3
    _, alive = psutil.wait_procs(processes, timeout=300)  # far past the lifetime: ended
    assert alive == []
    assert not pool.usable
    with leased(3) as fresh:
        assert fresh is not pool


def test_a_pool_leased_again_lives_a_whole_lifetime_from_its_last_return(
    monkeypatch: Any,
) -> None:
    monkeypatch.setattr(pools, "IDLE_LIFETIME_S", 3600.0)
    with leased(4) as pool:  # a size of its own, and never run: no process is started
        pass
    earlier = pool.expiry
    assert earlier is not None
    with leased(4) as again:
        assert again is pool
    earlier.function(*earlier.args)  # that idle time's end, come late: the pool lives on
    assert pool.usable
    with pools._idle_lock:
        assert pool in pools._idle[4]
    monkeypatch.setattr(pools, "IDLE_LIFETIME_S", 0.3)
    with leased(4) as again:
        assert again is pool
    deadline = time.monotonic() + 300
    while pool.usable:  # its own lifetime does end it
        assert time.monotonic() < deadline, "the idle pool never ended"
        time.sleep(0.05)
    with pools._idle_lock:
        assert pool not in pools._idle.get(4, [])


def test_after_a_cancel_the_pool_serves_the_next_evaluation_whole() -> None:
    plan = tiny_plan(conditions=["nominal"])
    short, long = plan.runs
    endless = plan.model_copy(
        update={"runs": (short, long.model_copy(update={"max_episode_steps": 100_000}))}
    )
    done: list[EpisodeResult] = []
    cancelled = evaluate(  # stopped once PickCube is done, in PushCube's first long episode
        endless,
        LocalDirectory(RANDOM),
        warm=True,
        on_episode=lambda _run, episode: done.append(episode),
        should_stop=lambda: len(done) >= 3,
    )
    pick, push = cancelled.conditions[0].tasks
    assert [e.failure for e in pick.episodes] == [None, None, None]
    assert [e.failure for e in push.episodes] == ["not_run"] * 3
    again = evaluate(plan, LocalDirectory(SCRIPTED), warm=True)
    assert [e.failure for t in again.conditions[0].tasks for e in t.episodes] == [None] * 6


def test_new_processes_run_the_setup_first(tmp_path: Path, monkeypatch: Any) -> None:
    marker = tmp_path / "set-up"
    monkeypatch.setattr(pools, "_process_setup", None)
    pools.setup_processes(_touch, str(marker))
    pool = WarmPool(1)
    try:
        pool.warm()
        assert marker.read_text() == "set up"
    finally:
        pool.close()


def test_a_daemonic_process_evaluates_in_itself() -> None:
    """A Celery prefork child may start no process: asked for warm workers, it runs the
    evaluation itself, whole."""
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    child = context.Process(target=_evaluate_in_child, args=(results,), daemon=True)
    child.start()
    try:
        failures, idle = results.get(timeout=600)
    finally:
        child.join(timeout=60)
    assert failures == [None, None, None]
    assert idle == 0


def _evaluate_in_child(results: Any) -> None:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"])
    result = evaluate(plan, LocalDirectory(SCRIPTED), workers=2, warm=True)
    episodes = result.conditions[0].tasks[0].episodes
    results.put(([e.failure for e in episodes], idle_pools()))


def idle_pools() -> int:
    """How many warm pools wait for an evaluation in this process."""
    with pools._idle_lock:
        return sum(len(idle) for idle in pools._idle.values())


def _touch(path: str) -> None:
    Path(path).write_text("set up")


def _ignore(_run: int, _episode: EpisodeResult) -> None:
    pass


def _never() -> bool:
    return False


LESSEE = """
import sys
from pathlib import Path
from evaluator.evaluation import evaluate
from evaluator.plan import build_plan
from evaluator.sources import LocalDirectory
from evaluator.suite import load_suite

suite = load_suite(Path(sys.argv[1]))
plan = build_plan(suite, "dev", tasks=["PickCube-v1"], conditions=["nominal"])
run = plan.runs[0].model_copy(update={"max_episode_steps": 100_000})
evaluate(plan.model_copy(update={"runs": (run,)}), LocalDirectory(Path(sys.argv[2])), warm=True)
"""


def test_an_evaluator_process_ends_with_its_lessee_and_stops_its_policy() -> None:
    """A killed worker leaves no evaluator process, nor its policy, running on."""
    lessee = subprocess.Popen(
        [sys.executable, "-c", LESSEE, str(HERE / "tiny_suite.yaml"), str(RANDOM)],
        cwd=REPO,
        start_new_session=True,
    )
    left: list[psutil.Process] = []
    try:
        deadline = time.monotonic() + 600  # start-up on a loaded machine
        while not (left := _evaluating(lessee.pid)):
            assert lessee.poll() is None, "the lessee ended before it evaluated"
            assert time.monotonic() < deadline, "no policy started"
            time.sleep(0.2)
        lessee.kill()
        lessee.wait(timeout=60)
        _, alive = psutil.wait_procs(left, timeout=pools.ORPHAN_GRACE_S * 4)
        assert not alive, [p.cmdline() for p in alive]
    finally:
        if lessee.poll() is None:
            lessee.kill()
        for process in left:
            with contextlib.suppress(psutil.Error):
                process.kill()


def _evaluating(pid: int) -> list[psutil.Process]:
    """The evaluator process under `pid` and everything under it, once a policy runs there."""
    try:
        below = psutil.Process(pid).children(recursive=True)
        commands = [" ".join(p.cmdline()) for p in below]
    except psutil.Error:
        return []
    evaluators = [p for p, c in zip(below, commands, strict=True) if "multiprocessing.spawn" in c]
    if not evaluators or not any("policy.py" in c for c in commands):
        return []
    return [p for p in below if p.pid != pid and p not in _trackers(below, commands)]


def _trackers(below: list[psutil.Process], commands: list[str]) -> list[psutil.Process]:
    return [p for p, c in zip(below, commands, strict=True) if "resource_tracker" in c]
