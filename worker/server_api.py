"""The worker's side of ``/internal/v1``: the only way a worker reaches the server.

A worker claims work, reports its attempt's start, progress and end, and asks for reconciling
passes, all over HTTP with the worker token. Nothing finished is lost to an outage: a claim or
a final report that cannot be delivered (server down, its database down, 503) is retried with
capped, jittered backoff, and a final report is written to the spool before it is sent: one
that outlasts its patience is sent again while the worker runs (`worker.spool_sender`), and
when it starts.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from pydantic import ValidationError
from tenacity import (
    RetryCallState,
    Retrying,
    retry_if_exception_type,
    stop_after_delay,
    stop_when_event_set,
    wait_random_exponential,
)

from internal_api.schemas import (
    Assignment,
    AttemptRef,
    ClaimIn,
    FinalReport,
    Progress,
    ProgressReport,
    ReconcileOut,
    ReportOut,
    RestartOut,
    RunningReport,
    Silent,
    State,
)
from worker.settings import WorkerSettings

log = logging.getLogger(__name__)

RETRYABLE_STATUS = frozenset({429, 500, 502, 503, 504})
WAIT_CAP_S = 10.0
VIDEO_PATIENCE_S = 15.0  # videos are a view of the result: not worth holding an attempt up
# (no heartbeat goes out meanwhile; the first video that cannot be stored ends the uploads)


class ServerUnavailable(Exception):
    """The server did not accept the request within the patience given (it may be down)."""


class WorkerRefused(Exception):
    """The server refused the worker itself (a wrong or revoked worker token): configuration."""


class _Retryable(Exception):
    def __init__(self, message: str, retry_after: float | None = None) -> None:
        super().__init__(message)
        self.retry_after = retry_after


@dataclass(frozen=True)
class Spooled:
    submission_id: int
    attempt: int
    report: FinalReport
    written: float = 0.0
    """When it was written to the spool (seconds since the epoch)."""


class Spool:
    """Final reports not yet accepted, one JSON file per attempt, written before sending."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory

    def _path(self, submission_id: int, attempt: int) -> Path:
        return self.directory / f"{submission_id}-{attempt}.json"

    def put(self, submission_id: int, attempt: int, report: FinalReport) -> None:
        self.directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        path = self._path(submission_id, attempt)
        tmp = path.with_suffix(".tmp")
        body = {
            "submission_id": submission_id,
            "attempt": attempt,
            "report": report.model_dump(mode="json"),
        }
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(body, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)

    def remove(self, submission_id: int, attempt: int) -> None:
        self._path(submission_id, attempt).unlink(missing_ok=True)

    def set_aside(self, submission_id: int, attempt: int) -> None:
        """Keep a report the server will never accept as `.bad`, out of the way of the others."""
        path = self._path(submission_id, attempt)
        if path.exists():
            path.rename(path.with_suffix(".bad"))

    def __iter__(self) -> Iterator[Spooled]:
        if not self.directory.is_dir():
            return
        for path in sorted(self.directory.glob("*.json")):
            try:
                body = json.loads(path.read_text())
                item = Spooled(
                    int(body["submission_id"]),
                    int(body["attempt"]),
                    FinalReport.model_validate(body["report"]),
                    path.stat().st_mtime,
                )
            except FileNotFoundError:  # delivered and removed meanwhile: another thread sends
                continue  # the spool too (the spool sender beside a run's own final report)
            except (OSError, ValueError, KeyError, TypeError, ValidationError) as exc:
                log.error("unreadable spooled report %s (%s); set aside as .bad", path, exc)
                with contextlib.suppress(FileNotFoundError):
                    path.rename(path.with_suffix(".bad"))
                continue
            yield item


class ServerAPI:
    """A client of the internal API; safe to share between threads."""

    def __init__(
        self,
        http: httpx.Client,
        *,
        spool: Spool,
        claim_patience_s: float = 300.0,
        report_patience_s: float = 900.0,
        stop: threading.Event | None = None,
    ) -> None:
        self._http = http
        self.spool = spool
        self._claim_patience = claim_patience_s
        self.report_patience_s = report_patience_s
        # a worker that gives up on its final report sooner does not wait longer for a video
        self._upload_patience = min(VIDEO_PATIENCE_S, report_patience_s)
        self.stop = stop or threading.Event()

    @classmethod
    def connect(
        cls, settings: WorkerSettings, *, transport: httpx.BaseTransport | None = None
    ) -> ServerAPI:
        """A client for the configured server (`transport`: tests run an app in-process)."""
        http = httpx.Client(
            base_url=f"{settings.server_url}/internal/v1",
            headers={"Authorization": f"Bearer {settings.worker_token.get_secret_value()}"},
            timeout=settings.request_timeout_s,
            # idle connections go before the server's keep-alive closes them (uvicorn: 5 s),
            # so that no report is sent on a connection being closed
            limits=httpx.Limits(keepalive_expiry=2.0),
            transport=transport,
        )
        return cls(
            http,
            spool=Spool(settings.resolved_spool_dir),
            claim_patience_s=settings.claim_patience_s,
            report_patience_s=settings.report_patience_s,
        )

    def close(self) -> None:
        self._http.close()

    # Work ------------------------------------------------------------------------------------

    def claim(self, worker: str) -> Assignment | None:
        """Claim the fairest queued submission; None when nothing can be claimed now."""
        body = ClaimIn(worker=worker).model_dump()
        response = self._send("POST", "/claims", body, patience=self._claim_patience)
        if response.status_code == 204:
            return None
        return Assignment.model_validate(response.json())

    def assignment(self, submission_id: int, attempt: int) -> Assignment | None:
        """A running attempt's evaluation again (a new watcher); None if it is not current."""
        response = self._send(
            "GET", _attempt(submission_id, attempt), None, patience=self._claim_patience
        )
        if response.status_code in (404, 409):
            return None
        return Assignment.model_validate(response.json())

    def restarted(self, worker: str) -> list[int]:
        """Tell the server this worker restarted: the attempts it had in flight end `error`."""
        path = f"/workers/{worker}/restarted"
        response = self._send("POST", path, None, patience=self._claim_patience)
        return RestartOut.model_validate(response.json()).ended

    # Reports ---------------------------------------------------------------------------------

    def running(
        self, submission_id: int, attempt: int, *, reason: str, deadline_s: float
    ) -> ReportOut | None:
        """`launching` → `running`; None when the attempt is no longer current."""
        body = RunningReport(reason=reason, deadline_s=deadline_s).model_dump()
        return self._report(submission_id, attempt, "running", body, self._claim_patience)

    def progress(self, submission_id: int, attempt: int, progress: Progress | None) -> ReportOut:
        """Progress and heartbeat, tried once: a missed beat is replaced by the next one.
        Raises ServerUnavailable when it was not delivered."""
        body = ProgressReport(progress=progress).model_dump()
        out = self._report(submission_id, attempt, "progress", body, 0.0)
        if out is None:  # no longer current: a re-run replaced it
            return ReportOut(applied=False, state=State.CANCELLED)
        return out

    def final(self, submission_id: int, attempt: int, report: FinalReport) -> State | None:
        """End the attempt; returns the submission's state, or None when the server could not
        be reached in time (the report stays in the spool and is sent again later)."""
        self.spool.put(submission_id, attempt, report)
        return self._deliver(submission_id, attempt, report, self.report_patience_s)[1]

    def flush_spool(self, *, patience_s: float | None = None, quiet_s: float = 0.0) -> int:
        """Send the reports kept in the spool, each retried for `patience_s` (default: the
        report patience), until one cannot be delivered; returns how many were settled
        (accepted, or no longer wanted). A report written less than `quiet_s` ago is left to
        the sender that is still retrying it; one the server refuses for good is set aside."""
        patience = self.report_patience_s if patience_s is None else patience_s
        settled = 0
        for item in self.spool:
            if self.stop.is_set():
                break
            if time.time() - item.written < quiet_s:
                continue
            try:
                done = self._deliver(item.submission_id, item.attempt, item.report, patience)[0]
            except RuntimeError as exc:  # a 4xx no retry can change (the worker token aside)
                log.error("the server refused a kept final report for good; set aside: %s", exc)
                self.spool.set_aside(item.submission_id, item.attempt)
                continue
            if not done:
                break  # out of reach: the others would wait as long
            settled += 1
        return settled

    def _deliver(
        self, submission_id: int, attempt: int, report: FinalReport, patience: float
    ) -> tuple[bool, State | None]:
        """Send a spooled report: (settled, the submission's state now)."""
        body = report.model_dump(mode="json")
        try:
            out = self._report(submission_id, attempt, "final", body, patience)
        except ServerUnavailable as exc:
            log.error(
                "the final report of submission %s attempt %s is kept in %s: %s",
                submission_id,
                attempt,
                self.spool.directory,
                exc,
            )
            return False, None
        self.spool.remove(submission_id, attempt)
        return True, out.state if out is not None else None

    def _report(
        self, submission_id: int, attempt: int, kind: str, body: Any, patience: float
    ) -> ReportOut | None:
        path = f"{_attempt(submission_id, attempt)}/{kind}"
        response = self._send("POST", path, body, patience=patience)
        if response.status_code in (404, 409):
            return None
        return ReportOut.model_validate(response.json())

    # Videos ----------------------------------------------------------------------------------

    def upload_video(self, submission_id: int, attempt: int, path: Path) -> bool:
        """Store one episode video of a running attempt on the server (its file name says
        which); False when the attempt is no longer current or running."""
        url = f"{_attempt(submission_id, attempt)}/videos/{path.name}"
        content = (path.read_bytes(), "video/mp4")
        response = self._send("PUT", url, None, patience=self._upload_patience, content=content)
        return response.status_code not in (404, 409)

    def upload_poster(self, submission_id: int, attempt: int, video: Path, poster: Path) -> bool:
        """Store the poster of an uploaded video; False when the attempt is no longer current
        or running."""
        url = f"{_attempt(submission_id, attempt)}/videos/{video.name}/poster"
        content = (poster.read_bytes(), "image/jpeg")
        response = self._send("PUT", url, None, patience=self._upload_patience, content=content)
        return response.status_code not in (404, 409)

    def upload_trajectory(self, submission_id: int, attempt: int, path: Path) -> bool:
        """Store one trajectory file (a task run's `.h5` or `.json`) of a running attempt on
        the server; False when the attempt is no longer current or running."""
        url = f"{_attempt(submission_id, attempt)}/trajectories/{path.name}"
        media = "application/x-hdf5" if path.suffix == ".h5" else "application/json"
        content = (path.read_bytes(), media)
        response = self._send("PUT", url, None, patience=self._upload_patience, content=content)
        return response.status_code not in (404, 409)

    # Reconciling -----------------------------------------------------------------------------

    def silent(self) -> list[AttemptRef]:
        """Running attempts whose worker stopped reporting."""
        response = self._send("GET", "/attempts/silent", None, patience=self._claim_patience)
        return Silent.model_validate(response.json()).attempts

    def reconcile(self) -> ReconcileOut:
        """One reconciling pass on the server (time-outs, lost attempts, wake-ups)."""
        response = self._send("POST", "/reconcile", None, patience=self._claim_patience)
        return ReconcileOut.model_validate(response.json())

    # Transport -------------------------------------------------------------------------------

    def _send(
        self,
        method: str,
        path: str,
        body: Any,
        *,
        patience: float,
        content: tuple[bytes, str] | None = None,
    ) -> httpx.Response:
        """One request, retried on outages for up to `patience` seconds (0: tried once);
        `content` (bytes, media type) is sent as the body instead of JSON."""
        request = f"{method} {self._http.base_url.path.rstrip('/')}{path}"
        retrying = Retrying(
            retry=retry_if_exception_type(_Retryable),
            wait=_wait,
            stop=stop_after_delay(patience) | stop_when_event_set(self.stop),
            sleep=self._sleep,
            before_sleep=_say_unavailable(request),
            reraise=True,
        )
        try:
            for try_ in retrying:
                with try_:
                    return self._once(method, path, body, content)
        except _Retryable as exc:
            raise ServerUnavailable(f"{method} {path}: {exc}") from None
        raise AssertionError("unreachable: tenacity either returns or raises")

    def _sleep(self, seconds: float) -> None:
        self.stop.wait(seconds)  # a worker told to stop does not sit out a backoff

    def _once(
        self, method: str, path: str, body: Any, content: tuple[bytes, str] | None = None
    ) -> httpx.Response:
        try:
            if content is not None:
                data, media_type = content
                response = self._http.request(
                    method, path, content=data, headers={"Content-Type": media_type}
                )
            else:
                response = self._http.request(method, path, json=body)
        except httpx.TransportError as exc:
            raise _Retryable(f"{type(exc).__name__}: {exc}") from None
        if response.status_code in RETRYABLE_STATUS:
            raise _Retryable(
                f"HTTP {response.status_code}: {response.text[:200]}",
                _retry_after(response.headers.get("retry-after")),
            )
        if response.status_code in (401, 403):
            raise WorkerRefused(f"the server refused the worker token ({response.status_code})")
        if response.status_code >= 400 and response.status_code not in (404, 409):
            raise RuntimeError(f"{method} {path}: HTTP {response.status_code}: {response.text}")
        return response


def _attempt(submission_id: int, attempt: int) -> str:
    return f"/submissions/{submission_id}/attempts/{attempt}"


def _retry_after(value: str | None) -> float | None:
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None


def _say_unavailable(request: str) -> Callable[[RetryCallState], None]:
    """One WARNING per refused attempt that will be tried again, with the wait: an outage
    shows in the worker's log as it happens, not only once the patience runs out."""

    def say(state: RetryCallState) -> None:
        exc = state.outcome.exception() if state.outcome is not None else None
        wait = state.next_action.sleep if state.next_action is not None else 0.0
        log.warning("server unavailable for %s: %s; trying again in %.1f s", request, exc, wait)

    return say


_jittered = wait_random_exponential(multiplier=0.5, max=WAIT_CAP_S)


def _wait(state: RetryCallState) -> float:
    """Capped, jittered exponential backoff that also honours the server's Retry-After."""
    delay = float(_jittered(state))
    exc = state.outcome.exception() if state.outcome is not None else None
    if isinstance(exc, _Retryable) and exc.retry_after is not None:
        delay = max(delay, min(exc.retry_after, WAIT_CAP_S))
    return delay
