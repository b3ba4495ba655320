"""Exit codes: scripts tell outcomes apart by them; and a call whose connection breaks."""

from __future__ import annotations

import httpx
import pytest

from manieval.client import Client, Unreachable
from manieval.errors import STATE_CODES, ExitCode


def test_every_exit_code_is_distinct() -> None:
    assert len({code.value for code in ExitCode}) == len(ExitCode.__members__)


def test_only_succeeded_exits_zero_and_each_final_state_has_its_code() -> None:
    assert set(STATE_CODES) == {"succeeded", "failed", "timed_out", "error", "cancelled"}
    assert [s for s, code in STATE_CODES.items() if code == ExitCode.OK] == ["succeeded"]
    assert len(set(STATE_CODES.values())) == len(STATE_CODES)


def broken_once(reads: list[str]) -> httpx.MockTransport:
    """A server whose first answer is lost with its connection, as when a reused connection is
    closed under the request; later ones are answered."""

    def answer(request: httpx.Request) -> httpx.Response:
        reads.append(request.method)
        if len(reads) == 1:
            raise httpx.ReadError("[Errno 104] Connection reset by peer", request=request)
        return httpx.Response(200, json={"username": "alice"})

    return httpx.MockTransport(answer)


def test_a_read_whose_connection_breaks_is_sent_once_more() -> None:
    reads: list[str] = []
    with Client("http://127.0.0.1:1", token="t", transport=broken_once(reads)) as client:
        assert client.me() == {"username": "alice"}
    assert reads == ["GET", "GET"]


def test_a_post_whose_connection_breaks_is_not_sent_again_and_says_why() -> None:
    reads: list[str] = []
    with Client("http://127.0.0.1:1", token="t", transport=broken_once(reads)) as client:
        with pytest.raises(Unreachable, match="Connection reset by peer"):
            client.call("POST", "/submissions", json={})
    assert reads == ["POST"]
