"""The evaluator's side of the policy protocol: a listening socket and typed calls with limits.

Every receive has a deadline (the per-call timeout, cut short to what is left of the policy's
time budget), frames from the policy are size-capped, and every way the policy can misbehave
surfaces as one of the exceptions below, never as a hang or a crash of the evaluator.

The budget counts only the time the evaluator waits for the policy's answers to `reset` and
`act`: never the evaluator's own work (imports, building and stepping the simulator), nor the
one-off set-up calls (`hello`, `task`), which their own timeouts bound.
"""

from __future__ import annotations

import os
import select
import socket
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from evaluator.results import EpisodeResult, FailureKind
from manieval_sdk.wire import (
    DEFAULT_MAX_FRAME_BYTES,
    HEADER,
    PROTOCOL_VERSION,
    PROTOCOL_VERSIONS,
    PeerClosed,
    ProtocolError,
    encode_frame,
    frame_length,
    send_message,
    unpack_message,
)

SOCKET_NAME = "policy.sock"
CHUNKS_SINCE = 2  # the protocol version that brought action chunks
ACTION_FIELDS = ("action", "actions")  # what an `action` reply may carry: one, or a chunk
POLL_S = 0.1  # how often a wait for the policy looks whether the evaluation was asked to stop
READ_AHEAD = 1 << 16  # bytes a read takes from the policy at most, beyond what it needs
# msgpack raises these without a message; what they mean, for the reason the policy is shown.
MSGPACK_ERRORS = {
    "FormatError": "a byte that starts no msgpack value (such as 0xc1, which msgpack never uses)",
    "StackError": "values nested deeper than the 1024 levels a decoder accepts",
}


class PolicyFailure(Exception):
    """The policy broke the evaluation: the kind and reason end up in the result document,
    with the record of the episode it broke, as far as it got, when it broke one."""

    def __init__(self, kind: FailureKind, reason: str) -> None:
        super().__init__(reason)
        self.kind: FailureKind = kind
        self.reason = reason
        self.episode: EpisodeResult | None = None


class PolicyRaised(Exception):
    """The policy's own code raised during a call; it ends the episode, not the evaluation."""


class Stopped(Exception):
    """The evaluation was asked to stop (a cancel, or another worker's abort): nobody's fault."""


class PolicyEndpoint:
    """A Unix socket the policy connects to, and the calls the evaluator makes over it."""

    def __init__(
        self,
        *,
        socket_dir: Path | None = None,
        max_frame_bytes: int = 1 << 20,
        budget_s: float = float("inf"),
    ) -> None:
        self._owned_dir = socket_dir is None
        self.socket_dir = Path(socket_dir or tempfile.mkdtemp(prefix="manieval-"))
        os.chmod(self.socket_dir, 0o700 if self._owned_dir else 0o755)
        self.path = self.socket_dir / SOCKET_NAME
        self.max_frame_bytes = max_frame_bytes
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(self.path))
        self._listener.listen(1)
        self._conn: socket.socket | None = None
        self._inbox = bytearray()  # bytes read from the policy and not yet taken
        self.budget_s = budget_s
        self.policy_time_s = 0.0  # charged time so far: waiting for answers to reset and act
        self.should_stop: Callable[[], bool] = lambda: False  # polled while waiting: Stopped
        self.protocol = PROTOCOL_VERSIONS[0]  # the version the policy chose at `hello`

    @property
    def address(self) -> str:
        """What the policy connects to (the SDK reads it from MANIEVAL_ENDPOINT)."""
        return f"unix://{self.path}"

    def accept(self, *, timeout: float, alive: Callable[[], bool]) -> None:
        """Wait for the policy to connect, giving up early if its process has exited."""
        deadline = time.monotonic() + timeout
        try:
            while self._conn is None:
                if self.should_stop():
                    raise Stopped()
                if not alive():
                    raise PolicyFailure("policy_crashed", "the policy exited before connecting")
                if time.monotonic() >= deadline:
                    raise PolicyFailure(
                        "policy_timeout", f"the policy did not connect within {timeout:g}s"
                    )
                self._listener.settimeout(POLL_S)
                try:
                    conn, _ = self._listener.accept()
                except TimeoutError:
                    continue
                conn.setblocking(False)
                self._conn = conn
        finally:
            self._listener.close()

    def call(
        self,
        message: dict[str, Any],
        *,
        expect: str,
        timeout: float,
        charged: bool = True,
        meanwhile: Callable[[], None] | None = None,
    ) -> dict[str, Any]:
        """Send one message and wait for its answer of type `expect`; a `charged` call's time
        counts against the budget, and the call is cut off where the budget ends.

        `meanwhile` is the evaluator's own work, run once the message is sent, while the policy
        thinks in its own process. A reply complete by the time it ends is charged only the
        sending (when within `meanwhile` it came is not known: the evaluator's time is never
        charged); any other reply is charged all the time since the message was sent, as the
        policy was still at work when the evaluator was done. A reply already complete is
        taken even where `meanwhile` ran past the call's deadline.
        """
        conn = self._require_conn()
        # Encoded before the try: an observation too large for the SDK is our problem, not the
        # policy's, and must not be recorded as its protocol error.
        frame = encode_frame(message, max_frame_bytes=DEFAULT_MAX_FRAME_BYTES)
        remaining = self.budget_s - self.policy_time_s if charged else float("inf")
        if remaining <= 0:
            raise self._budget_exhausted(message["type"])
        started = time.monotonic()
        deadline = started + min(timeout, remaining)
        uncharged = 0.0  # the evaluator's own time in the call, when the policy was done first
        try:
            self._refuse_unasked(conn)
            self._send(conn, frame, deadline)  # a policy that stops reading must not block it
            if meanwhile is not None:
                sent = time.monotonic()
                meanwhile()
                if self._has_whole_frame(conn):
                    uncharged = time.monotonic() - sent
            reply = self._receive(conn, deadline)
        except TimeoutError:
            if charged:
                self.policy_time_s += time.monotonic() - started
            if remaining < timeout:
                raise self._budget_exhausted(message["type"]) from None
            raise PolicyFailure(
                "policy_timeout", f"no answer to '{message['type']}' within {timeout:g}s"
            ) from None
        except (PeerClosed, BrokenPipeError, ConnectionResetError):
            raise PolicyFailure(
                "policy_crashed", f"the policy closed the connection during '{message['type']}'"
            ) from None
        except ProtocolError as exc:
            raise PolicyFailure("protocol_error", str(exc)) from None
        if charged:
            self.policy_time_s += time.monotonic() - started - uncharged
        if reply["type"] == "error":
            raise PolicyRaised(str(reply.get("message", "the policy reported an error"))[:2000])
        if reply["type"] != expect:
            raise PolicyFailure(
                "protocol_error",
                f"expected '{expect}' after '{message['type']}', got '{reply['type'][:64]}'",
            )
        return reply

    def hello(self, *, timeout: float) -> dict[str, Any]:
        """Handshake: offer our newest protocol version; the policy answers with the one to
        speak, any version we know up to it (version 1 policies answer 1, whatever offered)."""
        try:
            reply = self.call(
                {"type": "hello", "protocol": PROTOCOL_VERSION},
                expect="ready",
                timeout=timeout,
                charged=False,
            )
        except PolicyRaised as exc:
            raise PolicyFailure(
                "protocol_error", f"the policy refused the handshake: {exc}"
            ) from None
        spoken = reply.get("protocol")
        # The integer itself: True and 1.0 compare equal to 1 in Python, not on the wire.
        if type(spoken) is not int or spoken not in PROTOCOL_VERSIONS:
            known = " or ".join(str(version) for version in PROTOCOL_VERSIONS)
            raise PolicyFailure(
                "protocol_error",
                f"the policy speaks protocol {spoken!r}, not {known} (an integer)",
            )
        self.protocol = spoken
        return reply

    def act(
        self, obs: Any, *, timeout: float, meanwhile: Callable[[], None] | None = None
    ) -> dict[str, Any]:
        """Ask for an action: the answer's `action`, or under protocol 2 `actions` (a chunk),
        whichever it has; the caller validates them. Protocol 1 knows no `actions`: like any
        field it does not know, it is ignored."""
        reply = self.call(
            {"type": "act", "obs": obs}, expect="action", timeout=timeout, meanwhile=meanwhile
        )
        fields = ACTION_FIELDS if self.protocol >= CHUNKS_SINCE else ACTION_FIELDS[:1]
        return {name: reply[name] for name in fields if name in reply}

    # The connection never blocks (see `accept`): each read or write is one system call when
    # the socket is ready, as it mostly is, and a poll with a short timeout when it is not.

    def _send(self, conn: socket.socket, frame: bytes, deadline: float) -> None:
        view = memoryview(frame)
        while view:
            try:
                view = view[os.write(conn.fileno(), view) :]
            except BlockingIOError:  # the policy is not reading: wait for room, or the deadline
                self._wait_until_ready(conn, select.POLLOUT, deadline)

    def _receive(self, conn: socket.socket, deadline: float) -> dict[str, Any]:
        header = self._read(conn, HEADER.size, deadline)
        # A frame too large is refused before more of it than one read is taken.
        length = frame_length(header, max_frame_bytes=self.max_frame_bytes)
        payload = self._read(conn, length, deadline)
        try:
            return unpack_message(payload)
        except ProtocolError as exc:
            raise ProtocolError(explained(exc)) from None

    def _refuse_unasked(self, conn: socket.socket) -> None:
        """Before a call: anything the policy sent since its last reply is a frame nobody asked
        for (an answer sent ahead of its question, say), a breach of the protocol."""
        if not self._inbox:
            try:
                self._inbox += self._read_available(conn)
            except BlockingIOError:
                return
        raise ProtocolError("the policy sent a frame nobody asked for")

    def _has_whole_frame(self, conn: socket.socket) -> bool:
        """Whether a whole frame from the policy has arrived, without waiting for one."""
        try:
            self._inbox += self._read_available(conn)
        except (BlockingIOError, PeerClosed):  # nothing more yet; a close is seen when reading
            pass
        if len(self._inbox) < HEADER.size:
            return False
        length: int = HEADER.unpack_from(self._inbox)[0]
        return len(self._inbox) - HEADER.size >= length

    def _read_available(self, conn: socket.socket) -> bytes:
        """What has arrived, up to READ_AHEAD bytes; BlockingIOError when nothing has."""
        chunk = os.read(conn.fileno(), READ_AHEAD)
        if not chunk:
            raise PeerClosed("connection closed by the policy")
        return chunk

    def _read(self, conn: socket.socket, size: int, deadline: float) -> bytes:
        """The next `size` bytes from the policy. A read takes what has arrived, up to
        READ_AHEAD bytes: a small reply, header and all, in one system call; what it took past
        `size` waits in the inbox for the next read."""
        inbox = self._inbox
        while len(inbox) < size:
            try:
                chunk = os.read(conn.fileno(), max(size - len(inbox), READ_AHEAD))
            except BlockingIOError:  # nothing yet: wait for it, or the deadline
                self._wait_until_ready(conn, select.POLLIN, deadline)
                continue
            if not chunk:
                raise PeerClosed("connection closed by the policy")
            inbox += chunk
        data = bytes(inbox[:size])
        del inbox[:size]
        return data

    def _wait_until_ready(self, conn: socket.socket, events: int, deadline: float) -> None:
        """Wait, at most `POLL_S` at a time, until `conn` is ready for `events`."""
        poller = select.poll()
        poller.register(conn, events)
        poller.poll(self._next_wait(deadline) * 1000)

    def _next_wait(self, deadline: float) -> float:
        """How long the next wait on the socket may block: short, so a stop is seen at once."""
        if self.should_stop():
            raise Stopped()
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError()
        return min(POLL_S, remaining)

    def close(self) -> None:
        """Tell the policy to stop (best effort) and release the socket."""
        if self._conn is not None:
            try:
                self._conn.settimeout(1.0)
                send_message(self._conn, {"type": "close"})
            except OSError:
                pass
            self._conn.close()
            self._conn = None
        self._listener.close()
        self.path.unlink(missing_ok=True)
        if self._owned_dir:
            try:
                self.socket_dir.rmdir()
            except OSError:
                pass

    def _budget_exhausted(self, during: str) -> PolicyFailure:
        return PolicyFailure(
            "budget_exhausted",
            f"the evaluation's time budget ran out during '{during}': the policy took "
            f"{self.policy_time_s:.1f}s of the {self.budget_s:.1f}s it had here",
        )

    def _require_conn(self) -> socket.socket:
        if self._conn is None:
            raise RuntimeError("the policy is not connected")
        return self._conn


def explained(exc: ProtocolError) -> str:
    """The decoder's message, with what the error means when msgpack gave no detail."""
    text = str(exc)
    cause = exc.__context__  # kept by `raise ... from None`, which only hides it
    if text.endswith(": ") and cause is not None:
        return text + MSGPACK_ERRORS.get(type(cause).__name__, repr(cause))
    return text
