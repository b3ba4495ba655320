"""Warm evaluator processes: start-up (torch, ManiSkill, SAPIEN) paid once per machine, not per
shard.

An evaluation's shards run in the processes of a `WarmPool`. The pool's processes are spawned
once, import everything an episode needs, and stay: an evaluation leases a pool (`leased`),
runs its shards in it and gives it back for the next evaluation (a pool that no evaluation
leases for `IDLE_LIFETIME_S` ends its processes, to be started again on demand). A shard
then starts in milliseconds instead of seconds, so `--workers N` pays from the first episode
and a worker machine evaluates on all its cores. Each process is a separate interpreter, so
two shards (or two evaluations) never wait on one another's Python lock: in one process, two
threads stepping simulators run slower together than one alone.

Nothing of an evaluation outlives it in a process but imported modules: every episode rebuilds
its scene (`evaluator.sim`), environments are closed at the end of their task run, and each
shard starts its own policy process. docs/capacity.md ("Warm evaluator processes") has the
figures.

Spawned, not forked: torch and SAPIEN hold threads and Vulkan state that fork would copy.
"""

from __future__ import annotations

import atexit
import itertools
import multiprocessing
import os
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any

from evaluator.plan import EvaluationPlan
from evaluator.results import EpisodeResult
from evaluator.runner import (
    EpisodeCallback,
    OutputCallback,
    RunOptions,
    Shard,
    ShardOutcome,
    run_shard,
)
from evaluator.sources import PolicySource

EVENT_WAIT_S = 0.1
"""How often the lessee looks at its own stop while no shard reports."""
PARENT_CHECK_S = 0.5
"""How often an evaluator process checks that the process that started it is still there."""
ORPHAN_GRACE_S = 30.0
"""How long an orphaned evaluator process gives its shard to stop its policy, before it ends."""
END_WAIT_S = 30.0
"""How long the lessee waits, once every shard has returned, for the last events they sent."""
IDLE_LIFETIME_S = 600.0
"""How long a pool waits for its next evaluation before its processes end, giving their memory
back: a worker that evaluates nothing for a while holds none."""


ProcessSetup = tuple[Callable[..., object], tuple[Any, ...]]
_process_setup: ProcessSetup | None = None


def setup_processes(function: Callable[..., object], *args: Any) -> None:
    """Have every evaluator process started from now on run `function(*args)` first (a
    module-level function: it is named, not copied, into the new process). The service uses
    it to send the simulator's warnings to its log file there too."""
    global _process_setup
    _process_setup = (function, args)


class EvaluatorCrashed(RuntimeError):
    """An evaluator process died mid-evaluation (a simulator crash, or killed): the platform's
    failure, never the policy's."""


class PoolBroken(EvaluatorCrashed):
    """A process of the pool died while it was idle: nothing of the evaluation ran."""


class WarmPool:
    """`processes` evaluator processes that have imported torch and ManiSkill, one evaluation
    at a time."""

    def __init__(self, processes: int) -> None:
        if processes < 1:
            raise ValueError("a pool has at least one process")
        context = multiprocessing.get_context("spawn")
        self.processes = processes
        self._events: Any = context.Queue()
        self._stop: Any = context.Event()
        self._runs = itertools.count(1)
        self._executor = ProcessPoolExecutor(
            max_workers=processes,
            mp_context=context,
            initializer=_init_process,
            initargs=(self._events, self._stop, _process_setup, os.getpid()),
        )
        self.usable = True
        self.expiry: threading.Timer | None = None  # while idle: ends it at the end of its lifetime

    def warm(self) -> None:
        """Start every process and wait until each has imported what an episode needs."""
        # Submitted together, the tasks find no idle process: the executor starts one for each.
        for future in [self._executor.submit(_ready) for _ in range(self.processes)]:
            future.result()

    def run(
        self,
        plan: EvaluationPlan,
        source: PolicySource,
        shards: list[Shard],
        options: RunOptions,
        on_episode: EpisodeCallback,
        should_stop: Callable[[], bool],
        on_output: OutputCallback | None = None,
    ) -> list[ShardOutcome]:
        """Run the shards, one per process, reporting episodes as they end (and the policies'
        output, if asked); their outcomes in shard order. Any failure here leaves the pool
        unusable (its shards may still run)."""
        if len(shards) > self.processes:
            raise ValueError(f"{len(shards)} shards for {self.processes} processes")
        run_id = next(self._runs)
        self._stop.clear()
        self.usable = False  # until this run has ended cleanly
        try:
            echo = on_output is not None
            futures = [
                self._executor.submit(
                    _shard_in_process, run_id, plan, source, shard, options, index, echo
                )
                for index, shard in enumerate(shards)
            ]
        except BrokenProcessPool as exc:
            raise PoolBroken(f"an evaluator process ended while idle: {exc}") from exc
        try:
            self._pump(run_id, futures, on_episode, should_stop, on_output)
            outcomes = [future.result() for future in futures]
        except BrokenProcessPool as exc:
            self._stop.set()
            raise EvaluatorCrashed(f"an evaluator process ended mid-evaluation: {exc}") from exc
        except BaseException:
            self._stop.set()  # the shards still running end at their next step
            raise
        self.usable = True
        return outcomes

    def _pump(
        self,
        run_id: int,
        futures: list[Future[ShardOutcome]],
        on_episode: EpisodeCallback,
        should_stop: Callable[[], bool],
        on_output: OutputCallback | None,
    ) -> None:
        ended = 0  # shards whose last event arrived: results and events take different pipes
        all_done_at: float | None = None
        while True:
            if should_stop():
                self._stop.set()
            failed = any(f.done() and not f.cancelled() and f.exception() for f in futures)
            if failed:  # a shard raised (or its process died): the others need not go on
                self._stop.set()
            if all_done_at is None and all(future.done() for future in futures):
                all_done_at = time.monotonic()
            if ended == len(futures):
                return
            try:
                owner, kind, run_index, payload = self._events.get(timeout=EVENT_WAIT_S)
            except queue.Empty:
                if all_done_at is not None and (
                    failed or time.monotonic() - all_done_at > END_WAIT_S
                ):
                    return
                continue
            if owner != run_id:  # a late event of an earlier run of this pool
                continue
            if kind == "end":
                ended += 1
            elif kind == "episode":
                on_episode(run_index, EpisodeResult.model_validate(payload))
            elif kind == "abort":  # the policy broke: the other shards stop too
                self._stop.set()
            elif kind == "output" and on_output is not None:  # run_index: the shard's
                on_output(run_index, payload)

    def close(self) -> None:
        """Stop the processes; a shard still running is told to stop and not waited for."""
        self.usable = False
        self._stop.set()
        self._executor.shutdown(wait=False, cancel_futures=True)


_idle: dict[int, list[WarmPool]] = {}
_idle_lock = threading.Lock()


def run_warm(
    processes: int,
    plan: EvaluationPlan,
    source: PolicySource,
    shards: list[Shard],
    options: RunOptions,
    on_episode: EpisodeCallback,
    should_stop: Callable[[], bool],
    on_output: OutputCallback | None = None,
) -> list[ShardOutcome]:
    """`WarmPool.run` on a leased pool; once more on a new pool if the leased one turns out to
    have lost a process while idle (nothing had run yet)."""
    for attempt in (1, 2):
        try:
            with leased(processes) as pool:
                return pool.run(plan, source, shards, options, on_episode, should_stop, on_output)
        except PoolBroken:
            if attempt == 2:
                raise
    raise AssertionError("unreachable")


@contextmanager
def leased(processes: int) -> Iterator[WarmPool]:
    """A warm pool of `processes` for one evaluation: an idle one if there is, else a new one.
    It goes back to the idle ones if the evaluation ended cleanly, and is closed otherwise."""
    with _idle_lock:
        idle = _idle.get(processes, [])
        pool = idle.pop() if idle else None
        if pool is not None and pool.expiry is not None:
            pool.expiry.cancel()
            pool.expiry = None
    if pool is None:
        pool = WarmPool(processes)
    try:
        yield pool
    finally:
        if pool.usable:
            _keep_idle(pool)
        else:
            pool.close()


def _keep_idle(pool: WarmPool) -> None:
    """Put `pool` with the idle ones, to end after `IDLE_LIFETIME_S` unless leased before."""
    expiry = threading.Timer(IDLE_LIFETIME_S, _expire, args=(pool,))
    expiry.daemon = True
    with _idle_lock:
        pool.expiry = expiry
        _idle.setdefault(pool.processes, []).append(pool)
    expiry.start()


def _expire(pool: WarmPool) -> None:
    with _idle_lock:
        idle = _idle.get(pool.processes, [])
        if pool.expiry is not threading.current_thread() or pool not in idle:
            return  # leased (and maybe idle again) since this timer started
        idle.remove(pool)
        pool.expiry = None
    pool.close()


def can_start_processes() -> bool:
    """False in a daemonic process (a Celery prefork child), which may not have children."""
    return not multiprocessing.current_process().daemon


@atexit.register
def close_idle() -> None:
    """Close every idle pool (registered to run at exit)."""
    with _idle_lock:
        pools = [pool for pools in _idle.values() for pool in pools]
        _idle.clear()
    for pool in pools:
        if pool.expiry is not None:
            pool.expiry.cancel()
        pool.close()


_events: Any = None
_stop: Any = None
_shard_done = threading.Event()  # in an evaluator process: no shard is running
_shard_done.set()


def _init_process(events: Any, stop: Any, setup: ProcessSetup | None, parent: int) -> None:
    global _events, _stop
    _events, _stop = events, stop
    # A Ctrl-C in the terminal, or a service manager's SIGTERM, reaches the whole process
    # group: the lessee decides what stops, and the shard then stops its policy itself. Were
    # the lessee gone, `_end_with_parent` stops the shard.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    threading.Thread(
        target=_end_with_parent, args=(parent,), name="parent-watch", daemon=True
    ).start()
    if setup is not None:
        function, args = setup
        function(*args)
    import gymnasium  # noqa: F401
    import mani_skill.envs  # noqa: F401  (torch, SAPIEN and the task registry)


def _end_with_parent(parent: int) -> None:
    """An evaluator process outlives no lessee (one killed, say): once its parent is gone, the
    shard in flight stops at its next step, stopping its policy, and the process ends."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_S)
    _stop.set()
    _shard_done.wait(ORPHAN_GRACE_S)
    os._exit(1)


def _ready() -> bool:
    return True


def _shard_in_process(
    run_id: int,
    plan: EvaluationPlan,
    source: PolicySource,
    shard: Shard,
    options: RunOptions,
    index: int,
    echo: bool,
) -> ShardOutcome:
    def report(run_index: int, episode: EpisodeResult) -> None:
        _events.put((run_id, "episode", run_index, episode.model_dump(mode="json")))

    def output(data: bytes) -> None:
        _events.put((run_id, "output", index, data))

    _shard_done.clear()
    try:
        outcome = run_shard(
            plan,
            source,
            shard,
            options=options,
            on_episode=report,
            should_stop=_stop.is_set,
            on_output=output if echo else None,
        )
        if outcome.abort is not None:
            _events.put((run_id, "abort", outcome.abort[0], None))
    finally:
        _events.put((run_id, "end", None, None))  # after every event of the shard's
        _shard_done.set()
    return outcome
