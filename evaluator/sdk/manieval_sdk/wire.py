"""ManiEval wire format: length-prefixed msgpack frames, numpy arrays as an explicit extension.

A frame is a 4-byte big-endian unsigned length followed by that many bytes of msgpack. Arrays
travel as msgpack extension type 1 whose payload is the msgpack array
``[dtype, shape, data]``: a little-endian numpy dtype string from `ALLOWED_DTYPES`, a list of
non-negative ints, and the raw C-order bytes. Nothing here runs code on load: decoding yields
only dicts, lists, str, bytes, numbers, bools, None and numpy arrays. See docs/protocol.md.
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from typing import Any

import msgpack
import numpy as np

PROTOCOL_VERSION = 2  # the newest version this side speaks
PROTOCOL_VERSIONS = (1, 2)  # 2 is 1 plus action chunks; negotiated at `hello`
EXT_NDARRAY = 1
HEADER = struct.Struct(">I")
MAX_NDIM = 8
DEFAULT_MAX_FRAME_BYTES = 64 * 1024 * 1024

ALLOWED_DTYPES = frozenset(
    {"|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"}
)


class ProtocolError(Exception):
    """The peer sent something that is not a valid ManiEval frame or message."""


class FrameTooLarge(ProtocolError):
    """A frame's declared length exceeds the receiver's limit."""


class PeerClosed(ConnectionError):
    """The peer closed the connection."""


class CallTimeout(TimeoutError):
    """The peer did not answer before the deadline."""


_packers = threading.local()  # a msgpack Packer is reusable but not thread-safe


_DTYPES = {code: np.dtype(code) for code in ALLOWED_DTYPES}  # little-endian dtypes
_DTYPE_CODES = {dtype: code for code, dtype in _DTYPES.items()}
_DTYPES_BY_BYTES = {code.encode(): dtype for code, dtype in _DTYPES.items()}
_SHAPES: dict[tuple[int, ...], bytes] = {}  # shape -> its msgpack bytes, for common shapes


def _bin_header(size: int) -> bytes:
    if size < 0x100:
        return b"\xc4" + size.to_bytes(1, "big")
    if size < 0x10000:
        return b"\xc5" + size.to_bytes(2, "big")
    return b"\xc6" + size.to_bytes(4, "big")


def _encode_array(array: np.ndarray) -> msgpack.ExtType:
    # The payload is msgpack [dtype, shape, data], written out by hand: byte for byte what
    # a msgpack packer writes, at a fraction of the cost on the per-step path.
    code = _DTYPE_CODES.get(array.dtype)
    if code is None:
        dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        code = dtype.str
        if code not in ALLOWED_DTYPES:
            raise TypeError(
                f"arrays of dtype {array.dtype} cannot be sent; allowed: numeric and bool"
            )
        array = array.astype(dtype)
    shape = array.shape
    if len(shape) > MAX_NDIM:
        raise TypeError(f"arrays of more than {MAX_NDIM} dimensions cannot be sent")
    packed_shape = _SHAPES.get(shape)
    if packed_shape is None:
        packed_shape = msgpack.packb(list(shape))
        if len(_SHAPES) < 256:
            _SHAPES[shape] = packed_shape
    data = np.ndarray.tobytes(array)  # C order, whatever the layout; a masked array: its data
    return msgpack.ExtType(
        EXT_NDARRAY, b"\x93\xa3" + code.encode() + packed_shape + _bin_header(len(data)) + data
    )


def _default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return _encode_array(value)
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot encode a {type(value).__name__}")


def pack(message: Any) -> bytes:
    """Encode a message (dicts, lists, scalars, numpy arrays) to msgpack bytes."""
    packer = getattr(_packers, "outer", None)
    if packer is None:
        packer = _packers.outer = msgpack.Packer(default=_default, use_bin_type=True)
    try:
        payload: bytes = packer.pack(message)
    finally:
        packer.reset()  # a failed pack must not leave half a message in the buffer
    return payload


_SHAPE_UINTS = {0xCC: 1, 0xCD: 2, 0xCE: 4}  # msgpack uint8/16/32 tag: width (all < 2**40)
_BIN_TAGS = {0xC4: 1, 0xC5: 2, 0xC6: 4}  # msgpack bin8/16/32 tag: width of the length


def _decode_array(code: int, payload: bytes) -> np.ndarray:
    if code != EXT_NDARRAY:
        raise ProtocolError(f"unknown extension type {code}")
    dtype, shape, offset = _parse_packed(payload) or _parse_general(payload)
    size = len(payload) - offset
    if math.prod(shape) * dtype.itemsize != size:
        raise ProtocolError(f"array data is {size} bytes, shape {shape} needs a different size")
    array = np.frombuffer(payload, dtype=dtype, offset=offset).reshape(shape).copy()
    if dtype.kind == "b":
        # Bytes other than 0/1 in a bool array are undefined behaviour in numpy: normalise them.
        array = array.view(np.uint8).astype(np.bool_)
    return array if dtype.isnative else array.astype(dtype.newbyteorder("="))


def _parse_packed(payload: bytes) -> tuple[np.dtype, list[int], int] | None:
    """The dtype, shape and data offset of an array payload spelled as a msgpack packer (ours
    among them) writes it, read without building a decoder: the per-step path. None for any
    other spelling, which `_parse_general` then judges."""
    if len(payload) < 7 or payload[0] != 0x93 or payload[1] != 0xA3:  # [, a 3-byte str
        return None
    dtype = _DTYPES_BY_BYTES.get(payload[2:5])
    ndim = payload[5] - 0x90  # a fixarray
    if dtype is None or not 0 <= ndim <= MAX_NDIM:
        return None
    shape = []
    at = 6
    for _ in range(ndim):
        tag = payload[at] if at < len(payload) else -1
        if 0 <= tag < 0x80:  # a positive fixint
            shape.append(tag)
            at += 1
        elif tag in _SHAPE_UINTS:
            width = _SHAPE_UINTS[tag]
            shape.append(int.from_bytes(payload[at + 1 : at + 1 + width], "big"))
            at += 1 + width
        else:
            return None
    width = _BIN_TAGS.get(payload[at], 0) if at < len(payload) else 0
    start = at + 1 + width
    if not width or start > len(payload):
        return None
    if int.from_bytes(payload[at + 1 : start], "big") != len(payload) - start:
        return None  # not exactly the rest of the payload: the general path explains why
    return dtype, shape, start


def _parse_general(payload: bytes) -> tuple[np.dtype, list[int], int]:
    try:
        fields = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=True)
    except Exception as exc:
        raise ProtocolError(f"malformed array payload: {exc}") from None
    if not (isinstance(fields, list) and len(fields) == 3):
        raise ProtocolError("an array must be [dtype, shape, data]")
    dtype_str, shape, data = fields
    if not isinstance(dtype_str, str) or dtype_str not in ALLOWED_DTYPES:
        raise ProtocolError(f"array dtype {dtype_str!r} is not allowed")
    if not isinstance(shape, list) or len(shape) > MAX_NDIM:
        raise ProtocolError(f"array shape must be a list of at most {MAX_NDIM} ints")
    if not all(type(n) is int and 0 <= n < 2**40 for n in shape):
        raise ProtocolError("array shape entries must be non-negative ints")
    if not isinstance(data, bytes):
        raise ProtocolError("array data must be binary")
    return _DTYPES[dtype_str], shape, len(payload) - len(data)


def _no_timestamps(container: Any) -> Any:
    # msgpack decodes extension -1 as a Timestamp itself, without asking ext_hook.
    values = container.values() if isinstance(container, dict) else container
    if any(isinstance(value, msgpack.Timestamp) for value in values):
        raise ProtocolError("timestamps are not part of the protocol")
    return container


def unpack(payload: bytes) -> Any:
    """Decode msgpack bytes; raise ProtocolError on anything but well-formed data."""
    try:
        message = msgpack.unpackb(
            payload,
            raw=False,
            use_list=True,
            strict_map_key=True,
            ext_hook=_decode_array,
            list_hook=_no_timestamps,
            object_hook=_no_timestamps,
        )
        return _no_timestamps([message])[0]
    except ProtocolError:
        raise
    except Exception as exc:
        raise ProtocolError(f"malformed message: {type(exc).__name__}: {exc}") from None


def unpack_message(payload: bytes) -> dict[str, Any]:
    """Decode a message: a map with a string `type`."""
    message = unpack(payload)
    if not isinstance(message, dict) or not isinstance(message.get("type"), str):
        raise ProtocolError("a message must be a map with a string 'type'")
    return message


def encode_frame(message: Any, *, max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> bytes:
    """Header plus payload for one message; refuse payloads the receiver would refuse."""
    payload = pack(message)
    if len(payload) > max_frame_bytes:
        raise FrameTooLarge(f"frame of {len(payload)} bytes exceeds the {max_frame_bytes} limit")
    return HEADER.pack(len(payload)) + payload


def send_message(
    sock: socket.socket, message: Any, *, max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES
) -> None:
    """Send one message as a frame."""
    sock.sendall(encode_frame(message, max_frame_bytes=max_frame_bytes))


def _recv_exact(sock: socket.socket, size: int, deadline: float | None) -> bytes:
    chunks = bytearray()
    while len(chunks) < size:
        if deadline is not None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise CallTimeout("no complete answer before the deadline")
            sock.settimeout(remaining)
        try:
            chunk = sock.recv(min(size - len(chunks), 1 << 20))
        except TimeoutError:  # distinct classes before Python 3.10
            raise CallTimeout("no complete answer before the deadline") from None
        if not chunk:
            raise PeerClosed("connection closed by the peer")
        chunks += chunk
    return bytes(chunks)


def recv_message(
    sock: socket.socket,
    *,
    max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
    deadline: float | None = None,
) -> dict[str, Any]:
    """Receive one frame and decode it; `deadline` is a time.monotonic() value."""
    header = _recv_exact(sock, HEADER.size, deadline)
    length = frame_length(header, max_frame_bytes=max_frame_bytes)
    return unpack_message(_recv_exact(sock, length, deadline))


def frame_length(header: bytes, *, max_frame_bytes: int) -> int:
    """The payload length a frame's header announces, refused before any of the payload is
    read when it is over the limit or empty."""
    (length,) = HEADER.unpack(header)
    if length > max_frame_bytes:
        raise FrameTooLarge(f"frame of {length} bytes exceeds the {max_frame_bytes} limit")
    if length == 0:
        raise ProtocolError("empty frame")
    return int(length)
