"""The cluster's clock in the API-server double, and what the Job controller reads from it.

The Job controller takes its time from an injected `clock.Clock` (k8s.io/utils/clock, `jm.clock`
in pkg/controller/job/job_controller.go) and so does the double's model of it: a `ClusterClock`
that moves only when the double records a change (a second each, so that objects' timestamps
stay ordered at the API server's one-second precision) or when a test advances it. Nothing
waits on the wall clock: a test that needs the cluster to have run for two hours advances this
clock by two hours (`ApiServerDouble.advance`), and the controller acts at once on what is due.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

EPOCH = datetime(2026, 1, 1, tzinfo=UTC)
DEADLINE_EXCEEDED = "DeadlineExceeded"
DEADLINE_MESSAGE = "Job was active longer than specified deadline"
"""The condition's reason and message (`batch.JobReasonDeadlineExceeded`, `syncJob`)."""
_ENDED = frozenset({"Complete", "Failed", "FailureTarget", "SuccessCriteriaMet"})
_FORMAT = "%Y-%m-%dT%H:%M:%SZ"


@dataclass
class ClusterClock:
    """The time every controller of the double reads; starts at `EPOCH`."""

    elapsed_s: float = 0.0

    def now(self) -> datetime:
        return EPOCH + timedelta(seconds=self.elapsed_s)

    def stamp(self) -> str:
        """A timestamp for a change the cluster makes now: the clock moves on a second."""
        self.elapsed_s += 1
        return self.now().strftime(_FORMAT)

    def advance(self, seconds: float) -> None:
        """Let `seconds` pass (only the double's methods should call this: they act on it)."""
        if seconds < 0:
            raise ValueError("the cluster's clock does not go back")
        self.elapsed_s += seconds


def past_active_deadline(job: dict[str, Any], now: datetime) -> bool:
    """Whether the controller fails `job` for its deadline at `now`: `pastActiveDeadline` in
    pkg/controller/job/job_controller.go (activeDeadlineSeconds set, a startTime, not
    suspended, `clock.Since(startTime) >= activeDeadlineSeconds`), for a Job whose end the
    controller has not decided yet (`syncJob` looks for a finished condition first)."""
    spec, status = job.get("spec") or {}, job.get("status") or {}
    deadline, started = spec.get("activeDeadlineSeconds"), status.get("startTime")
    if deadline is None or started is None or spec.get("suspend"):
        return False
    if job["metadata"].get("deletionTimestamp") or decided(job):
        return False
    since = now - datetime.strptime(started, _FORMAT).replace(tzinfo=UTC)
    return since >= timedelta(seconds=deadline)


def decided(job: dict[str, Any]) -> bool:
    """Whether the controller has decided the Job's end (a finished condition: `syncJob`
    returns early on one, in pkg/controller/job/job_controller.go)."""
    conditions = (job.get("status") or {}).get("conditions") or []
    return any(c["type"] in _ENDED and c.get("status") == "True" for c in conditions)
