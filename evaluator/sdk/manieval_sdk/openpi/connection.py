"""The participant's openpi server: started as a child process, reached over a WebSocket on the
loopback interface, and spoken to in openpi's protocol with openpi-client's msgpack codec.

openpi's protocol: on connect the server sends one binary frame, its metadata (a map); then
each client frame is an observation (a map) and each server frame the answer, a map with
`actions` [H, D]. All frames are msgpack with numpy arrays as openpi-client's `msgpack_numpy`
spells them. When inference raises, the server sends the traceback as a text frame and closes
the connection with code 1011 (internal error).

openpi-client and websockets are imported only here, and only when a connection is opened: the
rest of the SDK needs numpy and msgpack alone.
"""

from __future__ import annotations

import inspect
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any, Protocol

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
RETRY_S = 0.2  # how often a server still starting is tried again
OPEN_TIMEOUT_S = 10.0  # the WebSocket handshake, once something listens
STOP_GRACE_S = 5.0
INSTALL_HINT = (
    "the openpi bridge needs openpi-client and websockets in the policy image: "
    "pip install 'manieval-sdk[openpi]' (or copy their wheels in: docs/policy-servers.md)"
)


class ServerError(RuntimeError):
    """The policy server failed a request, or cannot be reached; the message says how."""


def client_modules() -> tuple[Any, Any, Any]:
    """openpi-client's codec, websockets' synchronous client and its exceptions, or
    ServerError saying what to install."""
    try:
        from openpi_client import msgpack_numpy
        from websockets import exceptions
        from websockets.sync import client
    except ImportError as exc:
        raise ServerError(f"{INSTALL_HINT} ({exc})") from None
    return msgpack_numpy, client, exceptions


class Connection(Protocol):
    """A connection to a policy server: what it announced, and its answers."""

    metadata: Any
    broken: bool
    """True once the server closed it: the next request needs a new connection."""

    def infer(self, request: dict[str, Any]) -> Any: ...

    def close(self) -> None: ...


class ServerProcess:
    """The participant's server, a child of this process in the same process group: whoever
    stops the policy's group (the evaluator, the container engine) stops it too."""

    def __init__(self, command: Sequence[str]) -> None:
        self.command = tuple(command)
        try:
            self._process = subprocess.Popen(self.command, stdin=subprocess.DEVNULL)
        except OSError as exc:
            raise ServerError(
                f"cannot start the policy server {' '.join(self.command)!r}: {exc}"
            ) from None
        print(
            f"manieval_sdk.openpi: started the policy server (pid {self._process.pid}): "
            f"{' '.join(self.command)}",
            file=sys.stderr,
        )

    def exit_code(self) -> int | None:
        """Its exit status once it has ended; None while it runs."""
        return self._process.poll()

    def stop(self) -> None:
        """End it: SIGTERM, then SIGKILL after a grace period."""
        if self._process.poll() is not None:
            return
        self._process.terminate()
        try:
            self._process.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()


class OpenpiConnection:
    """One WebSocket connection to the server, with the metadata it announced."""

    def __init__(self, socket: Any, metadata: Any, url: str) -> None:
        self._socket = socket
        self.metadata = metadata
        self.url = url
        self.broken = False
        self._codec, _, self._errors = client_modules()
        self._packer = self._codec.Packer()

    @classmethod
    def open(
        cls, url: str, *, timeout: float, server: ServerProcess | None = None
    ) -> OpenpiConnection:
        """Connect, retrying while nothing listens yet, and read the metadata frame; all
        within `timeout` seconds, and not after `server` has exited."""
        codec, client, errors = client_modules()
        # websockets 15 reads proxies from the environment; a loopback address needs none.
        direct = {"proxy": None} if "proxy" in inspect.signature(client.connect).parameters else {}
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                socket = client.connect(
                    url,
                    open_timeout=max(0.1, min(remaining, OPEN_TIMEOUT_S)),
                    compression=None,
                    max_size=MAX_MESSAGE_BYTES,
                    **direct,
                )
                break
            except (OSError, TimeoutError):
                _not_exited(server, url)
                if time.monotonic() + RETRY_S > deadline:
                    raise ServerError(
                        f"nothing answered on {url} within {timeout:g} s: is the policy "
                        "server listening on that port? ([server] startup_timeout_s in the "
                        "mapping gives a slow one longer)"
                    ) from None
                time.sleep(RETRY_S)
            except errors.WebSocketException as exc:
                raise ServerError(f"{url} is not an openpi policy server: {exc}") from None
        try:
            frame = socket.recv(timeout=max(0.1, deadline - time.monotonic()))
        except TimeoutError:
            socket.close()
            raise ServerError(
                f"the policy server at {url} sent no metadata within {timeout:g} s of its start"
            ) from None
        except errors.ConnectionClosed as exc:
            raise ServerError(f"the policy server at {url} {_closed(exc)}") from None
        if isinstance(frame, str):
            socket.close()
            raise ServerError(_failure(frame))
        return cls(socket, codec.unpackb(frame), url)

    def infer(self, request: dict[str, Any]) -> Any:
        """The server's answer to one observation."""
        if self.broken:
            raise ServerError(f"the connection to {self.url} is closed")
        try:
            self._socket.send(self._packer.pack(request))
            answer = self._socket.recv()
        except self._errors.ConnectionClosed as exc:
            self.broken = True
            raise ServerError(f"the policy server {_closed(exc)}") from None
        if isinstance(answer, str):
            # openpi's server reports what inference raised as text, then closes (1011).
            self.close()
            print(f"manieval_sdk.openpi: the policy server failed:\n{answer}", file=sys.stderr)
            raise ServerError(_failure(answer))
        return self._codec.unpackb(answer)

    def close(self) -> None:
        """Close the connection (the server keeps running)."""
        self.broken = True
        self._socket.close()


def _not_exited(server: ServerProcess | None, url: str) -> None:
    code = None if server is None else server.exit_code()
    if code is not None:
        raise ServerError(
            f"the policy server exited with code {code} before it answered on {url} "
            "(its output is above)"
        )


def _closed(exc: Any) -> str:
    received = getattr(exc, "rcvd", None)
    if received is None:
        return "closed the connection without a close frame (did it crash?)"
    reason = f": {received.reason}" if received.reason else ""
    return f"closed the connection (code {received.code}{reason})"


def _failure(text: str) -> str:
    """The message a failed request gets: the last line of the server's traceback."""
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    last = lines[-1] if lines else "(no message)"
    return f"the policy server failed: {last}"
