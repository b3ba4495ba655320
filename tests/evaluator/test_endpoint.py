"""The evaluator's end of the protocol against a scripted peer: handshake, framing, malformed
frames, and what a call charges to the policy."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from evaluator.endpoint import PolicyEndpoint, PolicyFailure, Stopped
from manieval_sdk.serve import connect
from manieval_sdk.wire import encode_frame, recv_message

READY = encode_frame({"type": "ready", "protocol": 1})
ACTION = encode_frame({"type": "action", "action": [0.5]})
ZERO = encode_frame({"type": "action", "action": [0.0]})


class Peer:
    """A policy that reads the handshake, then writes the given chunks one at a time (a reply,
    pieces of one, several at once, or nothing) and stays connected without reading more."""

    def __init__(self, endpoint: PolicyEndpoint, *chunks: bytes) -> None:
        self._address = endpoint.address
        self._chunks = chunks
        self.hello: dict[str, object] | None = None  # what the evaluator sent first
        self.sent = threading.Event()  # every chunk is written
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with connect(self._address, timeout=10) as sock:
            self.hello = recv_message(sock)
            self.serve(sock)

    def serve(self, sock: socket.socket) -> None:
        """What the policy does once it has read the handshake."""
        for chunk in self._chunks:
            sock.sendall(chunk)
            time.sleep(0.01)  # separate writes, so the evaluator may see each on its own
        self.sent.set()
        self._done.wait(60)

    def stop(self) -> None:
        self._done.set()
        self._thread.join(5)


@pytest.fixture
def endpoint() -> Iterator[PolicyEndpoint]:
    endpoint = PolicyEndpoint()
    yield endpoint
    endpoint.close()


def handshake(endpoint: PolicyEndpoint, reply: bytes) -> Peer:
    peer = Peer(endpoint, reply)
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        endpoint.hello(timeout=10)
    finally:
        peer.stop()
    return peer


def frame(payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + payload


@pytest.mark.parametrize("version", [1, 2])
def test_the_policy_chooses_version_1_or_2_from_the_offer_of_2(
    endpoint: PolicyEndpoint, version: int
):
    assert endpoint.protocol == 1  # until a policy says otherwise
    peer = handshake(endpoint, encode_frame({"type": "ready", "protocol": version}))
    assert peer.hello == {"type": "hello", "protocol": 2}
    assert endpoint.protocol == version


@pytest.mark.parametrize("version", [True, 1.0, 2.0, "1", None, 0, 3])
def test_a_protocol_version_other_than_the_integers_1_and_2_is_refused(
    endpoint: PolicyEndpoint, version: object
):
    with pytest.raises(PolicyFailure, match="the policy speaks protocol") as failed:
        handshake(endpoint, encode_frame({"type": "ready", "protocol": version}))
    assert failed.value.kind == "protocol_error"
    assert repr(version) in failed.value.reason


def test_an_error_reply_to_hello_is_a_refused_handshake(endpoint: PolicyEndpoint):
    with pytest.raises(PolicyFailure, match="refused the handshake: v2 only") as failed:
        handshake(endpoint, encode_frame({"type": "error", "message": "v2 only"}))
    assert failed.value.kind == "protocol_error"


@pytest.mark.parametrize(
    ("payload", "detail"),
    [
        (b"\xc1" * 16, "FormatError: a byte that starts no msgpack value"),
        (b"\x91" * 5000 + b"\xc0", "StackError: values nested deeper than the 1024 levels"),
        (b"\x81\xa4type", "incomplete input"),
    ],
)
def test_a_malformed_reply_is_refused_with_a_reason_that_says_what_is_wrong(
    endpoint: PolicyEndpoint, payload: bytes, detail: str
):
    with pytest.raises(PolicyFailure) as failed:
        handshake(endpoint, frame(payload))
    assert failed.value.kind == "protocol_error"
    assert failed.value.reason.startswith("malformed message: ")
    assert detail in failed.value.reason
    assert not failed.value.reason.endswith(": ")


def test_a_stop_interrupts_a_call_that_is_waiting_for_the_policy(endpoint: PolicyEndpoint):
    stop = threading.Event()
    endpoint.should_stop = stop.is_set
    peer = Peer(endpoint)  # reads hello, never answers
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        threading.Timer(0.5, stop.set).start()
        with pytest.raises(Stopped):
            endpoint.hello(timeout=120)
    finally:
        peer.stop()


class Answering(Peer):
    """A policy that completes the handshake, then answers each `act` with an action: at once,
    or once `go` is set."""

    def __init__(
        self, endpoint: PolicyEndpoint, *, ready: bytes = READY, action: bytes = ZERO
    ) -> None:
        self.answered = threading.Event()
        self.go = threading.Event()
        self.go.set()
        self._ready, self._action = ready, action
        super().__init__(endpoint)

    def serve(self, sock: socket.socket) -> None:
        sock.sendall(self._ready)
        while recv_message(sock)["type"] == "act":
            self.go.wait(60)
            sock.sendall(self._action)
            self.answered.set()


@pytest.fixture
def answering(endpoint: PolicyEndpoint) -> Iterator[Answering]:
    """An `Answering` policy, connected and past the handshake."""
    peer = Answering(endpoint)
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        endpoint.hello(timeout=10)
        yield peer
    finally:
        endpoint.close()  # the policy's loop ends on `close`
        peer.stop()


def test_a_policy_still_at_work_when_the_evaluators_own_work_ends_is_charged_it_all(
    endpoint: PolicyEndpoint, answering: Answering
):
    charged_before = endpoint.policy_time_s
    answering.go.clear()  # the policy thinks until the evaluator's work is done, and then some

    def meanwhile() -> None:
        time.sleep(0.5)
        threading.Timer(0.2, answering.go.set).start()

    assert endpoint.act({"x": 1}, timeout=60, meanwhile=meanwhile) == {"action": [0.0]}
    assert endpoint.policy_time_s - charged_before >= 0.5 + 0.2


def test_the_evaluators_own_work_during_a_call_is_neither_charged_nor_timed_out(
    endpoint: PolicyEndpoint, answering: Answering
):
    charged_before = endpoint.policy_time_s
    timeout = 2.0
    ran = []

    def meanwhile() -> None:
        assert answering.answered.wait(60)  # the policy has answered: all that is left is ours
        time.sleep(timeout + 0.5)  # our own work, longer than the call's timeout
        ran.append(True)

    assert endpoint.act({"x": 1}, timeout=timeout, meanwhile=meanwhile) == {"action": [0.0]}
    assert ran == [True]
    assert endpoint.policy_time_s - charged_before < timeout


def test_a_reply_that_arrives_in_pieces_is_put_back_together(endpoint: PolicyEndpoint):
    pieces = [READY[:2], READY[2:5], READY[5:9], READY[9:]]
    peer = Peer(endpoint, *pieces)
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        assert endpoint.hello(timeout=30)["protocol"] == 1
    finally:
        peer.stop()


@pytest.mark.parametrize("writes", [[READY + ACTION], [READY, ACTION]], ids=["one", "two"])
def test_an_answer_sent_before_its_question_is_a_protocol_error(
    endpoint: PolicyEndpoint, writes: list[bytes]
):
    peer = Peer(endpoint, *writes)  # the handshake's reply, and an action nobody asked for
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        endpoint.hello(timeout=30)
        assert peer.sent.wait(60)  # it is all here, read with the handshake or still waiting
        with pytest.raises(PolicyFailure, match="a frame nobody asked for") as failed:
            endpoint.act({"x": 1}, timeout=30)
        assert failed.value.kind == "protocol_error"
    finally:
        peer.stop()


def test_a_policy_that_stops_reading_cannot_hold_a_call_past_its_timeout(
    endpoint: PolicyEndpoint,
):
    peer = Peer(endpoint, READY)  # then never reads again
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        endpoint.hello(timeout=30)
        big = np.zeros(8 << 20, dtype=np.uint8)  # far more than a socket's buffer holds
        with pytest.raises(PolicyFailure, match="no answer to 'act' within 1s") as failed:
            endpoint.act(big, timeout=1.0)
        assert failed.value.kind == "policy_timeout"
    finally:
        peer.stop()


@pytest.mark.parametrize(
    ("version", "fields"), [(1, {"action": [0.0]}), (2, {"action": [0.0], "actions": [[1.0]]})]
)
def test_an_actions_field_is_a_chunk_under_protocol_2_and_ignored_under_1(
    endpoint: PolicyEndpoint, version: int, fields: dict[str, object]
):
    both = encode_frame({"type": "action", "action": [0.0], "actions": [[1.0]], "why": "-"})
    peer = Answering(
        endpoint, ready=encode_frame({"type": "ready", "protocol": version}), action=both
    )
    try:
        endpoint.accept(timeout=10, alive=lambda: True)
        endpoint.hello(timeout=10)
        assert endpoint.act({"x": 1}, timeout=30) == fields
    finally:
        endpoint.close()
        peer.stop()
