"""What the browser tests share: Debian's Chromium through Playwright, and an app served by
uvicorn on a free loopback port in a thread."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import pytest
import uvicorn
from fastapi import FastAPI

T = TypeVar("T", bound=Any)
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
START_TIMEOUT_S = 120.0  # a generous bound on uvicorn starting on a busy machine
PATIENCE_MS = 120_000
"""How long a browser test's navigations and actions may take before they fail: Playwright's
own default, 30 s, is a page load on a busy machine. A bound, never a measure."""


def require_chromium() -> None:
    """Skip without Debian's Chromium, or fail under CI=true."""
    if CHROMIUM.exists():
        return
    message = f"Debian's Chromium is not installed at {CHROMIUM} (apt-get install chromium)"
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)


def patient(target: T) -> T:
    """`target` (a browser context, or a page of its own) waiting up to PATIENCE_MS for its
    navigations and actions."""
    target.set_default_navigation_timeout(PATIENCE_MS)
    target.set_default_timeout(PATIENCE_MS)
    return target


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def serving(app: FastAPI) -> Iterator[str]:
    """`app` on http://127.0.0.1:<free port> until the block ends; yields the base URL."""
    port = free_port()
    # No log_config: uvicorn would reconfigure this process's logging for later tests.
    config = uvicorn.Config(
        app, host="127.0.0.1", port=port, log_config=None, timeout_graceful_shutdown=5
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + START_TIMEOUT_S
    try:
        while not server.started:
            assert thread.is_alive(), "the server did not start"
            assert time.monotonic() < deadline, "the server did not start in time"
            time.sleep(0.02)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)
