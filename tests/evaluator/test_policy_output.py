"""The policy's own output passed on as it comes: in order, from its first byte, and bounded
whatever the policy prints."""

from __future__ import annotations

import os
import threading
import time

from evaluator.sources import LOG_TAIL_BYTES, LogTail, OutputEcho


def test_output_within_the_limit_is_passed_on_whole_and_in_order():
    pieces: list[bytes] = []
    echo = OutputEcho(pieces.append, limit=100)
    for piece in (b"loading weights\n", b"ready\n"):
        echo.feed(piece)
    echo.close()
    assert b"".join(pieces) == b"loading weights\nready\n"


def test_beyond_the_limit_only_the_last_bytes_follow_at_the_end_with_what_was_left_out():
    pieces: list[bytes] = []
    echo = OutputEcho(pieces.append, limit=10)
    echo.feed(b"0123456789abc")  # 3 bytes over
    assert b"".join(pieces) == b"0123456789"
    echo.feed(b"x" * (2 * LOG_TAIL_BYTES) + b"the end\n")
    assert b"".join(pieces) == b"0123456789"  # held back until the output ends
    echo.close()
    echo.close()  # once only
    left_out = 3 + 2 * LOG_TAIL_BYTES + len(b"the end\n") - LOG_TAIL_BYTES
    ending = b"".join(pieces).removeprefix(b"0123456789")
    note = f"\n[... {left_out} bytes of the policy's output left out ...]\n".encode()
    assert ending.startswith(note)
    assert ending.endswith(b"the end\n")
    assert len(ending) == len(note) + LOG_TAIL_BYTES
    echo.feed(b"late")  # after the end: nothing
    assert b"".join(pieces).endswith(b"the end\n")


def test_a_tail_passes_on_what_came_before_the_echo_then_the_rest_until_the_end():
    read, write = os.pipe()
    with os.fdopen(read, "rb") as stream:
        tail = LogTail(stream)
        os.write(write, b"before\n")
        deadline = time.monotonic() + 120  # a reader thread's first read, on a busy machine
        while tail.total_bytes < len(b"before\n"):  # drained by its thread: before the echo
            assert time.monotonic() < deadline, "the tail never read what was written"
            time.sleep(0.01)
        done = threading.Event()
        pieces: list[bytes] = []

        def collect(data: bytes) -> None:
            pieces.append(data)
            if data.endswith(b"after\n"):
                done.set()

        tail.echo(collect)
        os.write(write, b"after\n")
        os.close(write)
        assert done.wait(10)
        tail.join(10)
    assert b"".join(pieces) == b"before\nafter\n"
    assert tail.text() == "before\nafter\n"  # the tail is kept as before
