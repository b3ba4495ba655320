"""The policy side of the protocol: connect to the evaluator and answer its calls."""

from __future__ import annotations

import os
import socket
import sys
import time
import traceback
from typing import Any

import numpy as np

from manieval_sdk.policy import ActionChunks, Policy, TaskSpec
from manieval_sdk.seeding import episode_seed, reseed, task_seed
from manieval_sdk.wire import (
    DEFAULT_MAX_FRAME_BYTES,
    PROTOCOL_VERSION,
    PROTOCOL_VERSIONS,
    PeerClosed,
    encode_frame,
    recv_message,
)

ENDPOINT_ENV = "MANIEVAL_ENDPOINT"
CONNECT_TIMEOUT_S = 60.0
SDK_VERSION = "0.2.0"


def connect(endpoint: str, *, timeout: float = CONNECT_TIMEOUT_S) -> socket.socket:
    """Connect to `unix:///path` or `tcp://host:port`, retrying until the evaluator listens."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return _connect_once(endpoint)
        except (FileNotFoundError, ConnectionRefusedError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def _connect_once(endpoint: str) -> socket.socket:
    if endpoint.startswith("unix://"):
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.connect(endpoint[len("unix://") :])
        return sock
    if endpoint.startswith("tcp://"):
        host, _, port = endpoint[len("tcp://") :].rpartition(":")
        sock = socket.create_connection((host.strip("[]"), int(port)))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock
    raise ValueError(f"endpoint must be unix:///path or tcp://host:port, not {endpoint!r}")


def task_spec(fields: dict[str, Any]) -> TaskSpec:
    """Build a TaskSpec from the `task` message's `spec` map."""
    chunks = fields.get("action_chunks") or {}  # absent from protocol 1's spec
    return TaskSpec(
        env_id=fields["env_id"],
        obs_mode=fields["obs_mode"],
        control_mode=fields["control_mode"],
        control_freq=int(fields["control_freq"]),
        max_episode_steps=int(fields["max_episode_steps"]),
        action_low=np.asarray(fields["action_space"]["low"]),
        action_high=np.asarray(fields["action_space"]["high"]),
        observation_space=fields.get("observation_space", {}),
        extra=fields.get("extra", {}),
        action_chunks=ActionChunks(
            max_length=int(chunks.get("max_length", 1)), execute=int(chunks.get("execute", 1))
        ),
        instruction=str(fields.get("instruction", "")),
    )


def agreed_version(offered: Any) -> int:
    """The protocol version to speak, given the one the evaluator's `hello` names (its newest):
    the lower of the two sides' newest, as each speaks every version up to its newest."""
    if type(offered) is int and offered >= PROTOCOL_VERSIONS[0]:
        return min(offered, PROTOCOL_VERSION)
    return PROTOCOL_VERSIONS[0]


def action_reply(output: Any, spec: TaskSpec | None, *, protocol: int) -> dict[str, Any]:
    """The `action` reply for what `Policy.act` returned: one action, or a chunk of them.

    An array with one more dimension than the task's actions is a chunk. Only its first
    `spec.action_chunks.execute` actions go out, the ones the evaluator executes; where that is
    one (or the evaluator speaks protocol 1, which has no chunks), the first alone, as `action`.
    """
    action = np.asarray(output)
    if spec is None or action.ndim != len(spec.action_shape) + 1:
        return {"type": "action", "action": action}
    if len(action) == 0:
        raise ValueError(f"Policy.act returned an empty chunk of actions, shape {action.shape}")
    execute = spec.action_chunks.execute if protocol >= 2 else 1
    if execute == 1:
        return {"type": "action", "action": action[0]}
    return {"type": "action", "actions": action[:execute]}


class _Session:
    """The policy's side of one connection: the version agreed on and the current task."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.protocol = PROTOCOL_VERSIONS[0]
        self.spec: TaskSpec | None = None

    def handle(self, message: dict[str, Any]) -> dict[str, Any] | None:
        """The reply to one message from the evaluator (None: none, the connection ends)."""
        kind, policy = message["type"], self.policy
        if kind == "hello":
            self.protocol = agreed_version(message.get("protocol"))
            name = type(policy).__name__
            return {"type": "ready", "protocol": self.protocol, "sdk": SDK_VERSION, "name": name}
        if kind == "task":
            self.spec = task_spec(message["spec"])
            reseed(policy, task_seed(self.spec))
            policy.setup(self.spec)
            return {"type": "ok"}
        if kind == "reset":
            reseed(policy, episode_seed(message["obs"]))
            policy.reset(message["obs"], message.get("info", {}))
            return {"type": "ok"}
        if kind == "act":
            return action_reply(policy.act(message["obs"]), self.spec, protocol=self.protocol)
        if kind == "close":
            return None
        return {"type": "error", "message": f"unknown message type {kind!r}"}


def _error_reply(exc: BaseException) -> dict[str, Any]:
    lines = traceback.format_exception(type(exc), exc, exc.__traceback__)
    return {
        "type": "error",
        "message": f"{type(exc).__name__}: {exc}"[:2000],
        "traceback": "".join(lines)[-4000:],
    }


def serve(
    policy: Policy, endpoint: str | None = None, *, max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES
) -> None:
    """Serve `policy` to the evaluator at `endpoint` (default: $MANIEVAL_ENDPOINT) until closed."""
    address = endpoint or os.environ.get(ENDPOINT_ENV)
    if not address:
        sys.exit(f"manieval_sdk: set {ENDPOINT_ENV} (the evaluator sets it when it runs a policy)")
    sock = connect(address)
    session = _Session(policy)
    with sock:
        while True:
            try:
                message = recv_message(sock, max_frame_bytes=max_frame_bytes)
            except PeerClosed:
                return
            try:
                reply = session.handle(message)
                if reply is None:
                    return
                frame = encode_frame(reply, max_frame_bytes=max_frame_bytes)
            except Exception as exc:  # the policy's own bug: report it, keep serving
                traceback.print_exc()
                frame = encode_frame(_error_reply(exc), max_frame_bytes=max_frame_bytes)
            sock.sendall(frame)
