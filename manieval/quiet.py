"""The service's console keeps to the service: the simulator's own warnings go to a log file.

ManiSkill, gymnasium, SAPIEN and torch warn (Python ``warnings`` and their loggers) about
things a participant's run does, in the service's process: on the console of `manieval demo`
they would read as the service's problems, long after "serving". `quiet_third_party` sends
them, each distinct message once, to a log file instead; everything else is left as it was.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import warnings
from pathlib import Path
from typing import TextIO

from evaluator.pool import setup_processes

# Top-level packages whose warnings are theirs, not ours.
THIRD_PARTY = ("mani_skill", "gymnasium", "gym", "sapien", "torch", "trimesh", "transforms3d")
# The loggers they write to (ManiSkill's name has a trailing space).
THIRD_PARTY_LOGGERS = ("mani_skill ", "mani_skill", "gymnasium", "sapien", "torch", "trimesh")
WARNINGS_LOGGER = "manieval.third_party"
# ManiSkill sets SAPIEN's renderer (C++, straight to stderr) to this level when it starts.
RENDERER_LOG_ENV = "MS_RENDERER_LOG_LEVEL"


class Once(logging.Filter):
    """Lets each distinct message through once (a warning per episode is one warning)."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[tuple[str, str]] = set()
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.getMessage())
        with self._lock:
            if key in self._seen:
                return False
            self._seen.add(key)
            return True


def is_third_party(filename: str) -> bool:
    """Whether a warning was raised from inside one of the `THIRD_PARTY` packages."""
    parts = Path(filename).parts
    return any(package in parts for package in THIRD_PARTY)


def quiet_third_party(log_path: Path) -> logging.Handler:
    """Route the simulator's warnings and log records to `log_path`, each once; the handler."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(log_path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.addFilter(Once())
    sink = logging.getLogger(WARNINGS_LOGGER)
    sink.handlers[:] = [handler]
    sink.propagate = False
    sink.setLevel(logging.WARNING)
    for name in THIRD_PARTY_LOGGERS:
        # Set before ManiSkill is imported, its logger finds a handler and adds no console one.
        logger = logging.getLogger(name)
        logger.handlers[:] = [handler]
        logger.propagate = False
    os.environ.setdefault(RENDERER_LOG_ENV, "error")
    previous = warnings.showwarning

    def show(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: TextIO | None = None,
        line: str | None = None,
    ) -> None:
        if is_third_party(filename):
            text = warnings.formatwarning(message, category, filename, lineno, line).strip()
            sink.warning("%s", text)
        else:
            previous(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    setup_processes(quiet_third_party, log_path)  # the evaluator processes it starts, too
    return handler


class ConsoleLog(logging.StreamHandler):  # type: ignore[type-arg]
    """Log records on the current stderr (a live display may have replaced it meanwhile)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def service_logging(log_path: Path) -> None:
    """The demo's logging: every record (INFO and up) to `log_path`, warnings and errors of
    our own also on the console, the simulator's only in the file (once each)."""
    quiet_third_party(log_path)
    to_file = logging.FileHandler(log_path, encoding="utf-8")
    to_file.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    console = ConsoleLog()
    console.setLevel(logging.WARNING)
    console.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [to_file, console]
    root.setLevel(logging.INFO)
    logging.getLogger("uvicorn.access").setLevel(logging.WARNING)  # every poll, otherwise
