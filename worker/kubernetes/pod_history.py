"""What a Job's pods have shown across the looks of its watcher: which were seen alive, and
since when they wait to start. From it, the cluster's doing that ends an attempt while its Job
runs on: a pod evicted, preempted, refused by its node or lost ends it at once, and pods
unscheduled, pending, never created or whose image does not pull end it after the pending
timeout (`k8s_pending_timeout_s`), as `error` with the cluster's reason, never `timed_out`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from worker.kubernetes.status import STOPPED, PodView, Verdict, pending_verdict


@dataclass
class PodHistory:
    """The pods of one Job as its watcher saw them, look after look."""

    shards: int
    pending_timeout_s: float
    seen: frozenset[str] = frozenset()
    """The pods alive at the last look."""
    pending_since: float | None = None
    """Since when (monotonic) the pods have not all started; None while they all run."""

    def forget(self) -> None:
        """Start again, for a Job made anew."""
        self.seen, self.pending_since = frozenset(), None

    def stopped(
        self, view: PodView, job_runs: Callable[[], bool], warning: Callable[[], str]
    ) -> Verdict | None:
        """The cluster's doing, said as it says it: a pod evicted, preempted, refused or lost
        with its node (deleted or not); or pods not started past the pending timeout
        (`pending_verdict`: an image that does not pull, unschedulable, refused by a
        ResourceQuota, never created). None while the Job may still run. `job_runs` asks the
        API whether the Job still runs (only when a pod vanished)."""
        if view.disrupted is not None:
            return Verdict(STOPPED + view.disrupted)
        gone = sorted(self.seen - view.names)
        if gone and job_runs():
            # A live pod vanished while the Job runs on (not its deadline, which deletes pods
            # too): evicted and deleted, preempted, or garbage-collected with a lost node.
            return Verdict(f"{STOPPED}pod {gone[0]} was deleted (evicted, preempted, or lost)")
        if gone:
            return None  # the Job has just ended: the next look concludes it
        self.seen = view.alive
        now = time.monotonic()
        if view.started >= self.shards:
            self.pending_since = None
            return None
        if self.pending_since is None:
            self.pending_since = now
            return None
        waited = now - self.pending_since
        if waited <= self.pending_timeout_s:
            return None  # an image pull the kubelet retries, a node the autoscaler adds
        return pending_verdict(view, waited, warning)
