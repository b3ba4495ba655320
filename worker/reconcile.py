"""The worker's side of a reconciling pass: what only a worker can see.

The server decides (`server/submissions/reconcile.py`); a worker looks at what runs the
evaluations. Before the server's pass, a silent attempt whose Kubernetes Job still runs gets a
new watcher (and a heartbeat), so the evaluation is not thrown away; after it, containers and
Jobs of attempts that are no longer active are removed (a worker that crashed left them).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from internal_api.schemas import ReconcileOut
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

log = logging.getLogger(__name__)

Cleaner = Callable[[set[tuple[int, int]]], list[str]]
"""Removes runtime resources (containers, Jobs) of attempts not in the given active set."""
Resumer = Callable[[int, int], bool]
"""For a running attempt whose watcher went silent: True when its evaluation still exists
elsewhere (a Kubernetes Job) and a new watcher has been sent for it; raises when it cannot
tell (the attempt is then given a heartbeat and looked at again in the next pass)."""


@dataclass
class Report:
    server: ReconcileOut
    resumed: list[int] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)


def reconcile_pass(
    api: ServerAPI, *, cleaners: Sequence[Cleaner] = (), resume: Resumer | None = None
) -> Report:
    """Resume what still runs, ask the server for its pass, then clean up leftovers."""
    resumed: list[int] = []
    if resume is not None:
        for ref in api.silent():
            sid, attempt = ref.submission_id, ref.attempt
            try:
                still_there = resume(sid, attempt)
            except Exception:
                log.exception("cannot tell whether submission %s still runs; next pass", sid)
                still_there = True  # decided on the next pass, not thrown away now
            else:
                if still_there:
                    resumed.append(sid)
            if still_there:
                api.progress(sid, attempt, None)  # until the new watcher looks: not silent
    report = Report(server=api.reconcile(), resumed=resumed)
    active = {(ref.submission_id, ref.attempt) for ref in report.server.active}
    for clean in cleaners:
        try:
            report.removed += clean(active)
        except Exception:
            log.exception("cleaning leftovers failed; the next pass will try again")
    if report.resumed or report.removed:
        log.info("reconciled: resumed %s, removed %s", report.resumed, report.removed)
    return report


def runtime_cleaners(settings: WorkerSettings) -> list[Cleaner]:
    """What runs evaluations here: remove the containers and Jobs of attempts that are no
    longer active (a worker crashed, or lost its connection)."""
    cleaners: list[Cleaner] = []
    url = settings.docker_engine_url
    if url is not None:

        def clean_containers(active: set[tuple[int, int]]) -> list[str]:
            from worker.containers import attempt_key, engine, remove_leftovers

            keep = {attempt_key(sid, attempt) for sid, attempt in active}
            return remove_leftovers(engine(url), service=settings.service_id, keep=keep)

        cleaners.append(clean_containers)
    if settings.executor == "kubernetes":

        def clean_jobs(active: set[tuple[int, int]]) -> list[str]:
            from worker.kubernetes.client import kubernetes_executor

            executor = kubernetes_executor(settings)
            try:
                return executor.delete_orphans(keep=active)
            finally:
                executor.close()

        cleaners.append(clean_jobs)
    return cleaners


def job_resumer(settings: WorkerSettings, send: Callable[[int, int], None]) -> Resumer | None:
    """With Kubernetes, a silent attempt's Job may still be running (or done): `send` a new
    watcher for it rather than throwing the evaluation away. None for other executors."""
    if settings.executor != "kubernetes":
        return None

    def resume(submission_id: int, attempt: int) -> bool:
        from worker.kubernetes.client import kubernetes_executor

        executor = kubernetes_executor(settings)
        try:
            if executor.status(submission_id, attempt).phase == "missing":
                return False
        finally:
            executor.close()
        send(submission_id, attempt)
        return True

    return resume
