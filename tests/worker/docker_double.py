"""A stand-in Docker engine on a loopback port, for what no engine here can show: the requests
a GPU container is created with (Podman's Docker API accepts and drops them, and this machine
has no GPU). It answers the calls the docker executor makes to create, start, inspect, read and
remove one container, and records every request it receives."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import urlsplit

CONTAINER_ID = "c0ffee" * 10 + "abcd"


@dataclass
class Recorded:
    """What the engine was asked: (method, path, JSON body or None), in order."""

    requests: list[tuple[str, str, Any]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def created(self) -> dict[str, Any]:
        """The body of the one `containers/create` request."""
        with self.lock:
            bodies = [b for m, p, b in self.requests if m == "POST" and p.endswith("/create")]
        assert len(bodies) == 1, bodies
        created: dict[str, Any] = bodies[0]
        return created


def _version() -> dict[str, Any]:
    return {
        "ApiVersion": "1.43",
        "Version": "24.0.7",
        "Components": [{"Name": "Engine", "Version": "24.0.7", "Details": {}}],
    }


def _inspect(name: str) -> dict[str, Any]:
    return {
        "Id": CONTAINER_ID,
        "Name": f"/{name}",
        "Config": {"Tty": False, "Labels": {}},
        "State": {"Running": False, "ExitCode": 0, "OOMKilled": False},
    }


class _Handler(BaseHTTPRequestHandler):
    server: _Engine

    def log_message(self, format: str, *args: Any) -> None:
        pass  # quiet: the test reads `recorded`

    def _answer(self, status: int, body: Any = None, *, raw: bytes | None = None) -> None:
        data = raw if raw is not None else b"" if body is None else json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def _record(self) -> str:
        length = int(self.headers.get("Content-Length") or 0)
        body = json.loads(self.rfile.read(length)) if length else None
        path = urlsplit(self.path).path
        with self.server.recorded.lock:
            self.server.recorded.requests.append((self.command, path, body))
        if path.endswith("/containers/create"):
            self.server.name = self.path.partition("name=")[2] or "policy"
        return path

    def do_GET(self) -> None:
        path = self._record()
        if path.endswith("/version"):
            self._answer(200, _version())
        elif "/images/" in path:
            self._answer(200, {"Id": "sha256:" + "ab" * 32, "RepoDigests": []})
        elif path.endswith("/logs"):
            self._answer(200, raw=b"")
        elif path.endswith("/json"):
            self._answer(200, _inspect(self.server.name))
        else:
            self._answer(404, {"message": f"no route {path}"})

    def do_POST(self) -> None:
        path = self._record()
        if path.endswith("/containers/create"):
            self._answer(201, {"Id": CONTAINER_ID, "Warnings": []})
        elif path.endswith("/start"):
            self._answer(204)
        else:
            self._answer(404, {"message": f"no route {path}"})

    def do_DELETE(self) -> None:
        self._record()
        self._answer(204)


class _Engine(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.recorded = Recorded()
        self.name = "policy"


@contextmanager
def docker_double() -> Iterator[tuple[str, Recorded]]:
    """(engine URL, what it records) while the block runs."""
    engine = _Engine()
    thread = threading.Thread(target=engine.serve_forever, name="docker-double", daemon=True)
    thread.start()
    try:
        yield f"tcp://127.0.0.1:{engine.server_address[1]}", engine.recorded
    finally:
        engine.shutdown()
        engine.server_close()
        thread.join(5)
