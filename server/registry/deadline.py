"""A total deadline for every request one registry operation makes.

httpx's timeouts bound each socket operation, not a request: a registry that sends one byte
every few seconds holds a caller indefinitely. :func:`deadline_transport` caps every connect,
read and write at the time left until one shared :class:`Deadline`, so all the hops of a
resolve (manifest, token, index entries) end together when it passes.
"""

from __future__ import annotations

import functools
import ssl
import time
import typing

import httpcore
import httpx


class Deadline:
    """A point in time (monotonic clock) that a group of requests must finish by."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._at = time.monotonic() + seconds

    def remaining(self) -> float:
        """Seconds left; raises :class:`httpx.TimeoutException` once none are."""
        left = self._at - time.monotonic()
        if left <= 0:
            raise httpx.ReadTimeout(f"the deadline of {self.seconds:g} s has passed")
        return left

    def cap(self, timeout: float | None) -> float:
        left = self._at - time.monotonic()
        if left <= 0:
            raise httpcore.ReadTimeout(f"the deadline of {self.seconds:g} s has passed")
        return left if timeout is None else min(timeout, left)


class _Stream(httpcore.NetworkStream):
    def __init__(self, inner: httpcore.NetworkStream, deadline: Deadline) -> None:
        self._inner, self._deadline = inner, deadline

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._inner.read(max_bytes, self._deadline.cap(timeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._inner.write(buffer, self._deadline.cap(timeout))

    def close(self) -> None:
        self._inner.close()

    def start_tls(
        self,
        ssl_context: ssl.SSLContext,
        server_hostname: str | None = None,
        timeout: float | None = None,
    ) -> httpcore.NetworkStream:
        tls = self._inner.start_tls(ssl_context, server_hostname, self._deadline.cap(timeout))
        return _Stream(tls, self._deadline)

    def get_extra_info(self, info: str) -> typing.Any:
        return self._inner.get_extra_info(info)


class _Backend(httpcore.NetworkBackend):
    def __init__(self, deadline: Deadline) -> None:
        self._inner, self._deadline = httpcore.SyncBackend(), deadline

    def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: typing.Iterable[httpcore.SOCKET_OPTION] | None = None,
    ) -> httpcore.NetworkStream:
        stream = self._inner.connect_tcp(
            host, port, self._deadline.cap(timeout), local_address, socket_options
        )
        return _Stream(stream, self._deadline)

    def sleep(self, seconds: float) -> None:
        time.sleep(min(seconds, self._deadline.cap(seconds)))


@functools.cache
def _ssl_context() -> ssl.SSLContext:
    return httpx.create_ssl_context()  # the system's CAs, loaded once


class _DeadlineTransport(httpx.HTTPTransport):
    def __init__(self, deadline: Deadline) -> None:
        # httpx builds its pool with no way to pass a network backend: this is the pool it
        # would build for direct connections, over the capped backend.
        self._pool = httpcore.ConnectionPool(
            ssl_context=_ssl_context(), network_backend=_Backend(deadline)
        )


def deadline_transport(deadline: Deadline) -> httpx.HTTPTransport:
    """An HTTP transport (direct connections, system CAs) whose requests end by ``deadline``."""
    return _DeadlineTransport(deadline)
