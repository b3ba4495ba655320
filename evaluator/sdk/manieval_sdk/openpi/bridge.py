"""A ManiEval policy that is an openpi policy server: each observation goes to the server as
the mapping file says, and the server's action chunk comes back as this policy's answer."""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np

from manieval_sdk.openpi.connection import Connection, OpenpiConnection, ServerError, ServerProcess
from manieval_sdk.openpi.mapping import Mapping, loopback_url
from manieval_sdk.openpi.transform import (
    Size,
    action_chunk,
    build_request,
    check_sources,
    image_sizes,
    prompt_text,
)
from manieval_sdk.policy import Observation, Policy, TaskSpec

METADATA_SHOWN = 2000  # characters of the server's metadata printed to the log


class OpenpiBridge(Policy):
    """Answers the evaluator with what the participant's openpi server infers.

    A server that cannot be reached (it never listens, it exited) ends this process, so the
    evaluation stops with its output in the log; a request the server fails (a text frame and
    close 1011) fails that episode with the server's message, and the next request connects
    again.

    `connect` opens a connection (default: a WebSocket to `url`, waiting for `server` to
    listen); tests give one to a server in this process.
    """

    def __init__(
        self,
        mapping: Mapping,
        *,
        url: str | None = None,
        server: ServerProcess | None = None,
        connect: Callable[[], Connection] | None = None,
    ) -> None:
        self.mapping = mapping
        self.url = loopback_url(url or mapping.server.url)
        self.server = server
        self._connect = connect or self._open
        self._connection: Connection | None = None
        self._sizes: list[Size | None] = []
        self._prompt: str | None = None

    def setup(self, spec: TaskSpec) -> None:
        super().setup(spec)
        check_sources(self.mapping, spec.observation_space)
        metadata = self._connected().metadata
        self._sizes = image_sizes(self.mapping, metadata)
        self._prompt = prompt_text(self.mapping, spec.instruction or None)

    def act(self, obs: Observation) -> np.ndarray:
        request = build_request(obs, self.mapping, sizes=self._sizes, prompt=self._prompt)
        answer = self._connected().infer(request)
        # The chunk as the server gave it (at most `horizon`): the SDK sends the evaluator the
        # actions it executes (spec.action_chunks), the first alone where it takes no chunks.
        return action_chunk(answer, self.mapping.actions, self.spec.action_shape)

    def close(self) -> None:
        """Close the connection and stop the server this bridge started."""
        if self._connection is not None:
            self._connection.close()
        if self.server is not None:
            self.server.stop()

    def _open(self) -> Connection:
        timeout = self.mapping.server.startup_timeout_s
        return OpenpiConnection.open(self.url, timeout=timeout, server=self.server)

    def _connected(self) -> Connection:
        if self._connection is not None and not self._connection.broken:
            return self._connection
        try:
            self._connection = self._connect()
        except ServerError as exc:
            # Nothing will answer any request: stop here rather than fail every episode.
            raise SystemExit(f"manieval_sdk.openpi: {exc}") from None
        shown = repr(self._connection.metadata)
        if len(shown) > METADATA_SHOWN:
            shown = shown[:METADATA_SHOWN] + "..."
        print(f"manieval_sdk.openpi: connected to {self.url}; metadata: {shown}", file=sys.stderr)
        return self._connection
