"""A policy served in openpi's WebSocket protocol, as openpi's own server serves one
(openpi: src/openpi/serving/websocket_policy_server.py); written for this example.

The protocol: when a client connects the server sends one binary frame, its metadata (a map).
Then each binary frame from the client is an observation (a map) and the server answers each
with a binary frame, the policy's output: a map with `actions` [H, D] and `server_timing`. All
frames are msgpack, numpy arrays encoded by openpi-client's `msgpack_numpy`. When the policy
raises, the server sends the traceback as a text frame and closes the connection with code 1011
(internal error); it keeps serving other connections. GET /healthz answers "OK".
"""

from __future__ import annotations

import asyncio
import http
import logging
import time
import traceback
from typing import Any, Protocol

from openpi_client import msgpack_numpy
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

log = logging.getLogger("policy-server")


class InferencePolicy(Protocol):
    def infer(self, obs: dict[str, Any]) -> dict[str, Any]: ...


class WebsocketPolicyServer:
    """Serves `policy.infer` to one client after another (or several at once)."""

    def __init__(
        self,
        policy: InferencePolicy,
        *,
        host: str = "127.0.0.1",
        port: int = 8000,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        self.policy = policy
        self.host = host
        self.port = port
        self.metadata = metadata or {}

    def serve_forever(self) -> None:
        asyncio.run(self._run())

    async def _run(self) -> None:
        async with serve(
            self._handle,
            self.host,
            self.port,
            compression=None,
            max_size=None,
            process_request=_health_check,
        ) as server:
            log.info("serving on ws://%s:%d", self.host, self.port)
            await server.serve_forever()

    async def _handle(self, connection: ServerConnection) -> None:
        log.info("connection from %s", connection.remote_address)
        packer = msgpack_numpy.Packer()
        await connection.send(packer.pack(self.metadata))
        previous_ms: float | None = None
        while True:
            try:
                received = time.monotonic()
                obs = msgpack_numpy.unpackb(await connection.recv())
                started = time.monotonic()
                answer = dict(self.policy.infer(obs))
                timing = {"infer_ms": (time.monotonic() - started) * 1000}
                if previous_ms is not None:
                    timing["prev_total_ms"] = previous_ms
                answer["server_timing"] = timing
                await connection.send(packer.pack(answer))
                previous_ms = (time.monotonic() - received) * 1000
            except ConnectionClosed:
                log.info("connection from %s closed", connection.remote_address)
                return
            except Exception:
                log.exception("inference failed")
                await connection.send(traceback.format_exc())
                await connection.close(
                    code=CloseCode.INTERNAL_ERROR,
                    reason="Internal server error. Traceback included in previous frame.",
                )
                return


def _health_check(connection: ServerConnection, request: Request) -> Response | None:
    if request.path == "/healthz":
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None  # the WebSocket handshake goes on
