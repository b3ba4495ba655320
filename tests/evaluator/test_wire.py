"""The wire codec and framing of manieval_sdk.wire: what round-trips, what is refused, and how.

The decoder faces a policy we do not trust, so besides round trips this checks that every kind
of malformed input ends in ProtocolError (or PeerClosed/CallTimeout on a socket), never in any
other exception or a hang.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from manieval_sdk.wire import (
    ALLOWED_DTYPES,
    DEFAULT_MAX_FRAME_BYTES,
    EXT_NDARRAY,
    HEADER,
    MAX_NDIM,
    CallTimeout,
    FrameTooLarge,
    PeerClosed,
    ProtocolError,
    encode_frame,
    pack,
    recv_message,
    send_message,
    unpack,
    unpack_message,
)

DTYPES = sorted(ALLOWED_DTYPES)
SHAPES = [(), (0,), (5,), (2, 0, 3), (2, 3, 4), (1,) * MAX_NDIM]
# Short enough to keep the file fast, long enough for a loaded CI machine to deliver local bytes.
SHORT_WAIT_S = 0.2


# --- helpers ---------------------------------------------------------------------------------


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    """A connected pair of stream sockets: (sender, receiver)."""
    sender, receiver = socket.socketpair()
    with sender, receiver:
        yield sender, receiver


def frame(payload: bytes) -> bytes:
    """A frame around raw payload bytes, valid or not."""
    return HEADER.pack(len(payload)) + payload


def array_ext(dtype: Any, shape: Any, data: Any) -> msgpack.ExtType:
    """An extension-1 value with arbitrary (possibly invalid) fields."""
    inner: bytes = msgpack.packb([dtype, shape, data], use_bin_type=True)
    return msgpack.ExtType(EXT_NDARRAY, inner)


def message_with(value: Any) -> bytes:
    """Raw msgpack of a message carrying `value`, bypassing the encoder's checks."""
    payload: bytes = msgpack.packb({"type": "act", "value": value}, use_bin_type=True)
    return payload


def raw_ext_message(code: int, data: bytes) -> bytes:
    """A message whose `value` is an ext8 of any code, including negative ones."""
    ext = b"\xc7" + bytes([len(data)]) + struct.pack("b", code) + data
    return b"\x82\xa4type\xa3act\xa5value" + ext


def deadline_in(seconds: float) -> float:
    return time.monotonic() + seconds


def assert_same_array(received: Any, sent: np.ndarray) -> None:
    """Same shape, same values bit for bit, native little-endian allowed dtype, a real ndarray."""
    assert isinstance(received, np.ndarray)
    assert received.dtype.isnative
    assert received.dtype.str in ALLOWED_DTYPES
    expected = np.array(sent, dtype=sent.dtype.newbyteorder("<"), order="C")  # keeps 0-d
    assert received.dtype == expected.dtype
    assert received.shape == expected.shape
    assert received.tobytes() == expected.tobytes()


def assert_same(received: Any, sent: Any) -> None:
    """Structural equality where arrays compare bit for bit and tuples arrive as lists."""
    if isinstance(sent, np.ndarray):
        assert_same_array(received, sent)
    elif isinstance(sent, dict):
        assert isinstance(received, dict)
        assert received.keys() == sent.keys()
        for key, value in sent.items():
            assert_same(received[key], value)
    elif isinstance(sent, list | tuple):
        assert isinstance(received, list)
        assert len(received) == len(sent)
        for got, value in zip(received, sent, strict=True):
            assert_same(got, value)
    else:
        assert type(received) is type(sent)
        assert received == sent


# --- round trips -----------------------------------------------------------------------------


def test_nested_message_of_scalars_round_trips() -> None:
    message = {
        "type": "reset",
        "none": None,
        "flags": [True, False],
        "ints": [0, 1, -1, 127, -33, 2**31, 2**63 - 1, -(2**63), 2**64 - 1],
        "floats": [0.0, -0.0, 1.5, -2.25e300, float("inf"), float("-inf")],
        "text": "grüße, ロボット",
        "blob": b"\x00\xff\x01",
        "nested": {"a": {"b": [[], {}, [1, [2, [3]]]]}, "": "empty key"},
    }
    assert_same(unpack_message(pack(message)), message)


def test_nan_scalar_round_trips_as_nan() -> None:
    received = unpack_message(pack({"type": "x", "value": float("nan")}))
    assert isinstance(received["value"], float)
    assert received["value"] != received["value"]


def test_tuples_decode_as_lists() -> None:
    assert unpack(pack({"pair": (1, (2, 3))})) == {"pair": [1, [2, 3]]}


def test_numpy_scalars_encode_as_python_scalars() -> None:
    received = unpack(pack([np.float32(1.5), np.int64(-7), np.bool_(True), np.uint8(255)]))
    assert received == [1.5, -7, True, 255]
    assert [type(value) for value in received] == [float, int, bool, int]


@pytest.mark.parametrize(
    ("dtype", "shape"),
    [
        pytest.param(dtype, shape, id=f"{dtype}-{'x'.join(map(str, shape)) or '0d'}")
        for dtype in DTYPES
        for shape in SHAPES
    ],
)
def test_array_of_allowed_dtype_and_shape_round_trips(dtype: str, shape: tuple[int, ...]) -> None:
    size = int(np.prod(shape))
    sent = (np.arange(size) % 7 - 3).astype(dtype).reshape(shape)
    received = unpack_message(pack({"type": "act", "obs": {"x": sent}}))["obs"]["x"]
    assert_same_array(received, sent)


def test_zero_dim_bool_array_decodes_as_array() -> None:
    # ManiSkill's `extra/is_grasped` is such an array: policies receive it as a numpy.bool_.
    received = unpack(pack(np.array(True)))
    assert isinstance(received, np.ndarray)
    assert received.shape == ()
    assert received.dtype == np.bool_


@pytest.mark.parametrize("dtype", DTYPES)
def test_zero_dim_array_keeps_its_value(dtype: str) -> None:
    sent = np.array(1, dtype=dtype)
    assert np.asarray(unpack(pack(sent))).item() == sent.item()


def test_non_contiguous_array_round_trips() -> None:
    base = np.arange(60, dtype=np.float32).reshape(3, 4, 5)
    sent = base[::2, :, 1::2].transpose(2, 0, 1)
    assert not sent.flags.c_contiguous
    received = unpack(pack(sent))
    assert_same_array(received, sent)
    assert received.flags.c_contiguous


def test_fortran_ordered_array_round_trips_in_c_order() -> None:
    sent = np.asfortranarray(np.arange(12, dtype=np.int16).reshape(3, 4))
    received = unpack(pack(sent))
    assert_same_array(received, sent)
    np.testing.assert_array_equal(received, sent)


@pytest.mark.parametrize("dtype", [">i2", ">u2", ">i4", ">u4", ">i8", ">u8", ">f2", ">f4", ">f8"])
def test_big_endian_array_arrives_as_equal_native_little_endian_array(dtype: str) -> None:
    sent = (np.arange(6) - 2).astype(dtype).reshape(2, 3)
    received = unpack(pack(sent))
    assert received.dtype == np.dtype(dtype).newbyteorder("<")
    assert received.dtype.isnative
    np.testing.assert_array_equal(received, sent)


def test_encoder_writes_little_endian_dtype_string_and_c_order_bytes() -> None:
    sent = np.array([[1, 2], [3, 4]], dtype=">u2").T
    ext = msgpack.unpackb(pack(sent))
    assert ext.code == EXT_NDARRAY
    assert msgpack.unpackb(ext.data) == ["<u2", [2, 2], b"\x01\x00\x03\x00\x02\x00\x04\x00"]


def test_decoded_arrays_are_writable_copies() -> None:
    received = unpack(pack(np.zeros(4, dtype=np.float32)))
    received[0] = 1.0
    assert received[0] == 1.0


def test_bool_array_bytes_other_than_zero_and_one_decode_as_clean_booleans() -> None:
    payload = message_with(array_ext("|b1", [2, 3], bytes([0, 1, 2, 255, 128, 0])))
    received = unpack_message(payload)["value"]
    assert received.dtype == np.bool_
    assert received.tolist() == [[False, True, True], [True, True, False]]
    assert received.view(np.uint8).tolist() == [[0, 1, 1], [1, 1, 0]]
    assert int(received.sum()) == 4


# --- encoder refusals ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "array",
    [
        np.array([object(), 1], dtype=object),
        np.array(["a", "bc"]),
        np.array([b"a", b"bc"]),
        np.array([1 + 2j], dtype=np.complex64),
        np.array([1 + 2j], dtype=np.complex128),
        np.array(["2024-01-01"], dtype="datetime64[D]"),
        np.array([1], dtype="timedelta64[s]"),
        np.zeros(2, dtype=[("a", "<f4"), ("b", "<i4")]),
        np.zeros(2, dtype="V4"),
    ],
    ids=lambda array: array.dtype.str,
)
def test_encoder_refuses_non_numeric_arrays(array: np.ndarray) -> None:
    with pytest.raises(TypeError):
        pack({"type": "action", "action": array})


def test_encoder_refuses_arrays_of_more_than_max_ndim_dimensions() -> None:
    with pytest.raises(TypeError):
        pack(np.zeros((1,) * (MAX_NDIM + 1)))


def test_encoder_refuses_arbitrary_python_objects() -> None:
    with pytest.raises(TypeError):
        pack({"type": "x", "value": object()})


# --- decoder refusals ------------------------------------------------------------------------


@pytest.mark.parametrize("code", [0, 2, 5, 127])
def test_decoder_refuses_unknown_extension_code(code: int) -> None:
    with pytest.raises(ProtocolError, match="unknown extension"):
        unpack_message(message_with(msgpack.ExtType(code, b"\x00")))


def test_decoder_refuses_negative_extension_code() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(raw_ext_message(-5, b"\x00"))


def test_decoder_refuses_timestamp_extension() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(raw_ext_message(-1, struct.pack(">I", 1)))


@pytest.mark.parametrize(
    "dtype",
    [
        *[">f4", ">i8", "=f4", "f4", "float32", "<c8", "<c16", "|O", "<U1", "|S1", "|V4"],
        *["<f16", "<M8[D]", "", "<f4 ", b"<f4", 4, None, ["<f4"]],
    ],
)
def test_decoder_refuses_disallowed_dtype(dtype: Any) -> None:
    with pytest.raises(ProtocolError, match="dtype"):
        unpack_message(message_with(array_ext(dtype, [1], b"\x00" * 4)))


@pytest.mark.parametrize(("shape", "size"), [([3], 11), ([3], 13), ([2, 2], 12), ([], 0), ([0], 4)])
def test_decoder_refuses_data_of_the_wrong_size(shape: list[int], size: int) -> None:
    with pytest.raises(ProtocolError, match="bytes"):
        unpack_message(message_with(array_ext("<f4", shape, b"\x00" * size)))


@pytest.mark.parametrize("shape", [[-1], [2, -3], [-(2**63)]])
def test_decoder_refuses_negative_shape(shape: list[int]) -> None:
    with pytest.raises(ProtocolError, match="shape"):
        unpack_message(message_with(array_ext("|u1", shape, b"")))


@pytest.mark.parametrize(
    "shape", [[2.0], ["2"], [True], [None], [[2]], [b"\x02"], 2, "2", {"0": 2}, None, [2**40]]
)
def test_decoder_refuses_non_int_shape(shape: Any) -> None:
    with pytest.raises(ProtocolError, match="shape"):
        unpack_message(message_with(array_ext("|u1", shape, b"\x00\x00")))


def test_decoder_refuses_more_than_max_ndim_dimensions() -> None:
    with pytest.raises(ProtocolError, match="shape"):
        unpack_message(message_with(array_ext("|u1", [1] * (MAX_NDIM + 1), b"\x00")))


def test_decoder_refuses_huge_shape_with_a_zero_dimension() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(message_with(array_ext("<f8", [0, 2**39, 2**39, 2**39], b"")))


@pytest.mark.parametrize("data", ["\x00\x00\x00\x00", [0, 0, 0, 0], None, 0])
def test_decoder_refuses_non_binary_array_data(data: Any) -> None:
    with pytest.raises(ProtocolError, match="binary"):
        unpack_message(message_with(array_ext("|u1", [4], data)))


@pytest.mark.parametrize(
    "inner",
    [
        msgpack.packb(["<f4", [1]]),
        msgpack.packb(["<f4", [1], b"\x00" * 4, 0]),
        msgpack.packb({"dtype": "<f4", "shape": [1], "data": b"\x00" * 4}),
        msgpack.packb("<f4"),
        msgpack.packb(["<f4", [1], b"\x00" * 4]) + b"\x00",
        msgpack.packb(["<f4", [1], b"\x00" * 4])[:-1],
        b"",
        b"\xc1",
    ],
)
def test_decoder_refuses_malformed_array_payload(inner: bytes) -> None:
    with pytest.raises(ProtocolError):
        unpack_message(message_with(msgpack.ExtType(EXT_NDARRAY, inner)))


@pytest.mark.parametrize("value", [[], ["type", "act"], 1, "act", None, b"act", 1.5, True])
def test_decoder_refuses_non_map_message(value: Any) -> None:
    with pytest.raises(ProtocolError, match="map"):
        unpack_message(msgpack.packb(value, use_bin_type=True))


@pytest.mark.parametrize(
    "message",
    [{}, {"kind": "act"}, {"type": 1}, {"type": None}, {"type": b"act"}, {"type": ["act"]}],
)
def test_decoder_refuses_missing_or_non_str_type(message: dict[Any, Any]) -> None:
    with pytest.raises(ProtocolError, match="type"):
        unpack_message(msgpack.packb(message, use_bin_type=True))


def test_decoder_refuses_non_string_map_keys() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(msgpack.packb({"type": "act", 1: 2}))


def test_decoder_refuses_invalid_utf8_strings() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(b"\x81\xa4type\xa2\xff\xfe")


def test_decoder_refuses_every_truncation_of_a_valid_message() -> None:
    payload = pack({"type": "act", "obs": {"qpos": np.arange(9, dtype=np.float32)}, "n": 300})
    for cut in range(len(payload)):
        with pytest.raises(ProtocolError):
            unpack_message(payload[:cut])


def test_decoder_refuses_trailing_bytes_after_a_message() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(pack({"type": "ok"}) + b"\xc0")


def test_decoder_refuses_empty_payload() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(b"")


def test_decoder_refuses_deeply_nested_payload() -> None:
    with pytest.raises(ProtocolError):
        unpack_message(b"\x91" * 100_000 + b"\xc0")


# --- framing ---------------------------------------------------------------------------------


def test_encode_frame_prefixes_payload_with_big_endian_length() -> None:
    message = {"type": "ok"}
    encoded = encode_frame(message)
    payload = pack(message)
    assert encoded == len(payload).to_bytes(4, "big") + payload


def test_encode_frame_accepts_payload_exactly_at_the_limit() -> None:
    message = {"type": "x", "blob": b"\x00" * 100}
    size = len(pack(message))
    assert len(encode_frame(message, max_frame_bytes=size)) == size + 4


def test_encode_frame_refuses_payload_over_the_limit() -> None:
    message = {"type": "x", "blob": b"\x00" * 100}
    size = len(pack(message))
    with pytest.raises(FrameTooLarge):
        encode_frame(message, max_frame_bytes=size - 1)


def test_frame_too_large_is_a_protocol_error() -> None:
    assert issubclass(FrameTooLarge, ProtocolError)


def test_timeouts_and_closes_are_the_standard_exceptions() -> None:
    assert issubclass(CallTimeout, TimeoutError)
    assert issubclass(PeerClosed, ConnectionError)


def test_sdk_default_frame_limit_is_64_mib() -> None:
    assert DEFAULT_MAX_FRAME_BYTES == 64 * 1024 * 1024


def test_message_round_trips_over_a_socketpair(pair: tuple[socket.socket, socket.socket]) -> None:
    sender, receiver = pair
    message = {"type": "act", "obs": {"qpos": np.linspace(0, 1, 9, dtype=np.float32)}}
    send_message(sender, message)
    assert_same(recv_message(receiver, deadline=deadline_in(5)), message)


def test_recv_message_reads_back_to_back_frames_in_order(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.sendall(encode_frame({"type": "a"}) + encode_frame({"type": "b"}))
    assert recv_message(receiver, deadline=deadline_in(5)) == {"type": "a"}
    assert recv_message(receiver, deadline=deadline_in(5)) == {"type": "b"}


def test_recv_message_assembles_a_frame_sent_in_pieces(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    data = encode_frame({"type": "action", "action": np.arange(7, dtype=np.float32)})

    def trickle() -> None:
        for index in range(len(data)):
            sender.sendall(data[index : index + 1])
            if index % 8 == 0:
                time.sleep(0.001)

    thread = threading.Thread(target=trickle)
    thread.start()
    try:
        received = recv_message(receiver, deadline=deadline_in(5))
    finally:
        thread.join()
    assert_same_array(received["action"], np.arange(7, dtype=np.float32))


def test_recv_message_refuses_empty_frame(pair: tuple[socket.socket, socket.socket]) -> None:
    sender, receiver = pair
    sender.sendall(HEADER.pack(0))
    with pytest.raises(ProtocolError, match="empty"):
        recv_message(receiver, deadline=deadline_in(5))


def test_recv_message_refuses_frame_over_the_limit_from_its_header(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.sendall(HEADER.pack(1025))  # no payload follows: the header alone must be refused
    with pytest.raises(FrameTooLarge):
        recv_message(receiver, max_frame_bytes=1024, deadline=deadline_in(5))


def test_recv_message_refuses_frame_over_the_default_limit(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.sendall(HEADER.pack(DEFAULT_MAX_FRAME_BYTES + 1))
    with pytest.raises(FrameTooLarge):
        recv_message(receiver, deadline=deadline_in(5))


def test_recv_message_accepts_frame_exactly_at_the_limit(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    data = encode_frame({"type": "x", "blob": b"\x01" * 1000})
    sender.sendall(data)
    received = recv_message(receiver, max_frame_bytes=len(data) - 4, deadline=deadline_in(5))
    assert received["blob"] == b"\x01" * 1000


def test_recv_message_refuses_malformed_payload(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.sendall(frame(b"\xc1\xc1"))
    with pytest.raises(ProtocolError):
        recv_message(receiver, deadline=deadline_in(5))


def test_recv_message_refuses_frame_that_is_not_a_message(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.sendall(frame(msgpack.packb([1, 2, 3])))
    with pytest.raises(ProtocolError):
        recv_message(receiver, deadline=deadline_in(5))


@pytest.mark.parametrize("sent", [1, 2, 3, 4, 7])
def test_recv_message_times_out_when_the_peer_stops_mid_frame(
    pair: tuple[socket.socket, socket.socket], sent: int
) -> None:
    sender, receiver = pair
    sender.sendall(frame(b"\x81\xa4type\xa2ok" + b"\x00" * 10)[:sent])
    with pytest.raises(CallTimeout):  # a wait past the deadline would hang to the suite's timeout
        recv_message(receiver, deadline=time.monotonic() + SHORT_WAIT_S)


def test_recv_message_times_out_when_the_peer_sends_nothing(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    _, receiver = pair
    with pytest.raises(CallTimeout):
        recv_message(receiver, deadline=deadline_in(SHORT_WAIT_S))


def test_recv_message_with_a_past_deadline_times_out_at_once(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.sendall(encode_frame({"type": "ok"}))
    with pytest.raises(CallTimeout):
        recv_message(receiver, deadline=time.monotonic() - 1.0)


@pytest.mark.parametrize("sent", [0, 2, 4, 9])
def test_recv_message_raises_peer_closed_on_eof(
    pair: tuple[socket.socket, socket.socket], sent: int
) -> None:
    sender, receiver = pair
    sender.sendall(frame(b"\x81\xa4type\xa2ok" + b"\x00" * 10)[:sent])
    sender.shutdown(socket.SHUT_WR)
    with pytest.raises(PeerClosed):
        recv_message(receiver, deadline=deadline_in(5))


def test_recv_message_without_deadline_raises_peer_closed_on_eof(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    sender, receiver = pair
    sender.close()
    with pytest.raises(PeerClosed):
        recv_message(receiver)


# --- property tests --------------------------------------------------------------------------

SAMPLE_MESSAGES = [
    pack({"type": "ready", "protocol": 1, "sdk": "0.1.0", "name": "Scripted"}),
    pack({"type": "action", "action": np.linspace(-1, 1, 7, dtype=np.float32)}),
    pack(
        {
            "type": "act",
            "obs": {
                "agent": {"qpos": np.zeros(9, np.float32), "qvel": np.ones(9, np.float32)},
                "extra": {"is_grasped": np.array([True]), "ids": np.arange(4, dtype=">i8")},
            },
        }
    ),
    pack({"type": "error", "message": "ValueError: boom", "traceback": "..."}),
]


def mutated(
    draw: st.DrawFn, payload: bytes, *, changes: int, within: int | None = None
) -> bytearray:
    """`payload` with up to `changes` bytes overwritten, inserted or deleted (at offsets up to
    `within`, if given)."""
    data = bytearray(payload)
    for _ in range(draw(st.integers(0, changes))):
        position = draw(st.integers(0, len(data) if within is None else min(len(data), within)))
        action = draw(st.sampled_from(["set", "insert", "delete"]))
        byte = draw(st.integers(0, 255))
        if action == "set" and position < len(data):
            data[position] = byte
        elif action == "insert":
            data.insert(position, byte)
        elif position < len(data):
            del data[position]
    return data


@st.composite
def corrupted_payloads(draw: st.DrawFn) -> bytes:
    """A valid payload with a few bytes overwritten, inserted or deleted, maybe cut short."""
    data = mutated(draw, draw(st.sampled_from(SAMPLE_MESSAGES)), changes=6)
    cut = draw(st.integers(0, len(data)))
    return bytes(data[: len(data) if draw(st.booleans()) else cut])


fuzz_payloads = st.one_of(st.binary(max_size=256), corrupted_payloads())


@settings(max_examples=300, deadline=None)
@given(payload=fuzz_payloads)
def test_unpack_message_on_arbitrary_bytes_returns_a_message_or_raises_protocol_error(
    payload: bytes,
) -> None:
    try:
        message = unpack_message(payload)
    except ProtocolError:
        return
    assert isinstance(message, dict)
    assert isinstance(message["type"], str)


@st.composite
def stream_bytes(draw: st.DrawFn) -> bytes:
    """What a misbehaving peer might write: noise, or frames with right or wrong lengths."""
    payload = draw(fuzz_payloads)
    header = draw(
        st.one_of(
            st.just(HEADER.pack(len(payload))),
            st.integers(0, 2**32 - 1).map(HEADER.pack),
            st.binary(max_size=4),
        )
    )
    return draw(st.sampled_from([header + payload, payload, header]))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=stream_bytes(), close=st.booleans())
def test_recv_message_on_arbitrary_bytes_returns_a_message_or_raises_a_wire_error(
    data: bytes, close: bool
) -> None:
    sender, receiver = socket.socketpair()
    with sender, receiver:
        sender.sendall(data)
        if close:
            sender.shutdown(socket.SHUT_WR)
        try:
            message = recv_message(receiver, max_frame_bytes=4096, deadline=time.monotonic() + 0.02)
        except (ProtocolError, PeerClosed, CallTimeout):
            pass
        else:
            assert isinstance(message, dict)
            assert isinstance(message["type"], str)


array_dtypes = st.sampled_from(DTYPES).map(np.dtype)
wire_arrays = hnp.arrays(
    dtype=st.one_of(array_dtypes, array_dtypes.map(lambda dtype: dtype.newbyteorder(">"))),
    shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4),
)
leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(allow_nan=False),
    st.text(max_size=8),
    st.binary(max_size=8),
    wire_arrays,
)
values = st.recursive(
    leaves,
    lambda children: st.one_of(
        st.lists(children, max_size=4),
        st.dictionaries(st.text(max_size=6), children, max_size=4),
    ),
    max_leaves=12,
)
messages = st.builds(
    lambda kind, body: {**body, "type": kind},
    st.text(max_size=10),
    st.dictionaries(st.text(max_size=6), values, max_size=4),
)


@settings(max_examples=100, deadline=None)
@given(message=messages)
def test_pack_and_unpack_message_round_trip_generated_messages(message: dict[str, Any]) -> None:
    assert_same(unpack_message(pack(message)), message)


# --- the array payload, written and read by hand on the per-step path -----------------------


def msgpack_array_payload(array: np.ndarray) -> bytes:
    """What a msgpack packer writes for an array's [dtype, shape, data]: the reference."""
    little = array.astype(array.dtype.newbyteorder("<"))
    return msgpack.packb(  # type: ignore[no-any-return]
        [little.dtype.str, list(array.shape), little.tobytes()], use_bin_type=True
    )


def ext_payload(packed: bytes) -> bytes:
    """The payload of the one ndarray extension in a packed message."""
    ext = msgpack.unpackb(packed, ext_hook=lambda code, data: (code, data))
    assert ext[0] == EXT_NDARRAY
    return ext[1]  # type: ignore[no-any-return]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(
    "shape",
    # Data lengths either side of msgpack's bin8/bin16/bin32 boundaries; shape entries either
    # side of its fixint/uint8/uint16/uint32 boundaries.
    [(), (0,), (1,), (255,), (256,), (65535,), (65536,), (127, 1), (128, 1), (1, 256, 1)],
)
def test_array_payload_is_what_a_msgpack_packer_writes(dtype: str, shape: tuple[int, ...]) -> None:
    array = np.arange(int(np.prod(shape)), dtype=np.uint8).astype(dtype).reshape(shape)
    assert ext_payload(pack(array)) == msgpack_array_payload(array)


@pytest.mark.parametrize("shape", [(70000, 1), (1, 1, 65536 * 2)])
def test_array_payload_spells_large_shapes_as_a_msgpack_packer_does(
    shape: tuple[int, ...],
) -> None:
    array = np.zeros(shape, dtype="|u1")
    assert ext_payload(pack(array)) == msgpack_array_payload(array)


@pytest.mark.parametrize(
    ("dtype", "shape", "spelling"),
    [
        ("<f4", [2, 3], "str8 dtype"),
        ("<f4", [2, 3], "uint64 shape entries"),
        ("<f4", [2, 3], "bin32 data"),
        ("|b1", [4], "array32 outer list"),
    ],
)
def test_arrays_spelled_other_ways_by_other_packers_decode_the_same(
    dtype: str, shape: list[int], spelling: str
) -> None:
    array = np.arange(int(np.prod(shape))).astype(dtype).reshape(shape)
    data = array.tobytes()
    dtype_bytes = b"\xd9" + bytes([len(dtype)]) + dtype.encode()  # str8
    fixstr = bytes([0xA0 | len(dtype)]) + dtype.encode()
    shape_bytes = bytes([0x90 | len(shape)]) + b"".join(
        (b"\xcf" + n.to_bytes(8, "big")) if spelling == "uint64 shape entries" else bytes([n])
        for n in shape
    )
    bin_bytes = (
        b"\xc6" + len(data).to_bytes(4, "big") if spelling == "bin32 data" else b"\xc4"
    ) + (b"" if spelling == "bin32 data" else bytes([len(data)]))
    outer = b"\xdc\x00\x03" if spelling == "array32 outer list" else b"\x93"
    inner = outer + (dtype_bytes if spelling == "str8 dtype" else fixstr) + shape_bytes
    inner += bin_bytes + data
    message = msgpack.packb(
        {"type": "act", "value": msgpack.ExtType(EXT_NDARRAY, inner)}, use_bin_type=True
    )
    assert_same_array(unpack_message(message)["value"], array)


def test_array_data_shorter_or_longer_than_its_length_field_is_refused() -> None:
    payload = bytearray(ext_payload(pack(np.zeros(3, np.float32))))
    for change in (b"\x00", b""):
        broken = bytes(payload[:-1]) if not change else bytes(payload) + change
        message = msgpack.packb(
            {"type": "act", "value": msgpack.ExtType(EXT_NDARRAY, broken)}, use_bin_type=True
        )
        with pytest.raises(ProtocolError):
            unpack_message(message)


@st.composite
def mutated_array_payloads(draw: st.DrawFn) -> bytes:
    """A canonical array payload with a few bytes overwritten, inserted or deleted."""
    array = draw(wire_arrays)
    # Mostly in the first bytes: the dtype, shape and length, where spellings differ.
    return bytes(mutated(draw, ext_payload(pack(array)), changes=4, within=24))


def decoded_or_refusal(payload: bytes) -> Any:
    message = msgpack.packb(
        {"type": "act", "value": msgpack.ExtType(EXT_NDARRAY, payload)}, use_bin_type=True
    )
    try:
        return unpack_message(message)["value"]
    except ProtocolError:
        return ProtocolError


def reference_decoding(payload: bytes) -> Any:
    """The array payload judged by msgpack itself, as the protocol specifies it."""
    try:
        fields = msgpack.unpackb(payload, raw=False)
    except Exception:
        return ProtocolError
    if not (isinstance(fields, list) and len(fields) == 3):
        return ProtocolError
    dtype, shape, data = fields
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES or not isinstance(data, bytes):
        return ProtocolError
    if not isinstance(shape, list) or len(shape) > MAX_NDIM:
        return ProtocolError
    if not all(type(n) is int and n >= 0 for n in shape):
        return ProtocolError
    if int(np.prod(shape, dtype=object)) * np.dtype(dtype).itemsize != len(data):
        return ProtocolError
    array = np.frombuffer(data, dtype=dtype).reshape(shape)
    if array.dtype.kind == "b":
        array = array.view(np.uint8).astype(np.bool_)
    return array.astype(array.dtype.newbyteorder("="))


@settings(max_examples=400, deadline=None)
@given(payload=mutated_array_payloads())
@example(payload=msgpack.packb([[1], [2], b"\x00\x00"]))  # a dtype that is not a string
def test_the_fast_array_reader_judges_every_payload_as_msgpack_does(payload: bytes) -> None:
    got, expected = decoded_or_refusal(payload), reference_decoding(payload)
    if expected is ProtocolError:
        assert got is ProtocolError
    else:
        assert_same_array(got, expected)


def test_a_masked_array_sends_its_data_as_it_always_has() -> None:
    masked = np.ma.masked_array([1.0, 2.0, 3.0], mask=[False, True, False], dtype=np.float32)
    received = unpack_message(pack({"type": "act", "obs": masked}))["obs"]
    assert_same_array(received, np.array([1.0, 2.0, 3.0], dtype=np.float32))
