"""Final reports kept in the spool are sent again while the worker runs, not only at its start.

A worker cut off from the server for longer than its report patience (a network partition, a
long outage of the server) keeps the attempt's final report in its spool and goes on. A
thread of its own tries the spool again every ``MANIEVAL_SPOOL_RETRY_S`` seconds, so the
report lands soon after the link returns, whether or not the worker gets new work, and never
holds up an evaluation. Each pass tries each kept report once (the next pass is the retry),
stops at the first that cannot be delivered, and leaves alone a report written less than the
report patience ago: its writer is still retrying it. What the server no longer wants (the
attempt was ended and run again elsewhere meanwhile: 409) is dropped, as at a start.
"""

from __future__ import annotations

import logging
import threading

from worker.server_api import ServerAPI

log = logging.getLogger(__name__)


def resend_pass(api: ServerAPI) -> int:
    """Try each report kept longer than the report patience once; how many were settled."""
    return api.flush_spool(patience_s=0.0, quiet_s=api.report_patience_s)


class SpoolSender:
    """A daemon thread that runs `resend_pass` every `every_s` seconds until `stop()`, with
    a client of its own (`api`, closed at the stop)."""

    def __init__(self, api: ServerAPI, *, every_s: float) -> None:
        self.api = api
        self.every_s = every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="manieval-spool", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """End the thread (within one request's timeout) and close its client."""
        self._stop.set()
        self.api.stop.set()  # a pass in a backoff returns at once
        if self._thread.is_alive():
            self._thread.join(timeout)
        self.api.close()

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                settled = resend_pass(self.api)
            except Exception:  # the worker goes on; the next pass tries again
                log.exception("sending the kept final reports failed")
                continue
            if settled:
                log.info("sent %s kept final reports", settled)
