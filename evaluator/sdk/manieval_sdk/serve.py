"""The policy side of the protocol: connect to the evaluator and answer its calls."""

from __future__ import annotations

import os
import socket
import sys
import time
import traceback
from typing import Any

import numpy as np

from manieval_sdk.policy import Policy, TaskSpec
from manieval_sdk.seeding import episode_seed, reseed, task_seed
from manieval_sdk.wire import (
    DEFAULT_MAX_FRAME_BYTES,
    PROTOCOL_VERSION,
    PeerClosed,
    encode_frame,
    recv_message,
)

ENDPOINT_ENV = "MANIEVAL_ENDPOINT"
CONNECT_TIMEOUT_S = 60.0
SDK_VERSION = "0.1.0"


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
        instruction=str(fields.get("instruction", "")),
    )


def _handle(policy: Policy, message: dict[str, Any]) -> dict[str, Any] | None:
    kind = message["type"]
    if kind == "hello":
        return {
            "type": "ready",
            "protocol": PROTOCOL_VERSION,
            "sdk": SDK_VERSION,
            "name": type(policy).__name__,
        }
    if kind == "task":
        spec = task_spec(message["spec"])
        reseed(policy, task_seed(spec))
        policy.setup(spec)
        return {"type": "ok"}
    if kind == "reset":
        reseed(policy, episode_seed(message["obs"]))
        policy.reset(message["obs"], message.get("info", {}))
        return {"type": "ok"}
    if kind == "act":
        action = np.asarray(policy.act(message["obs"]))
        return {"type": "action", "action": action}
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
    with sock:
        while True:
            try:
                message = recv_message(sock, max_frame_bytes=max_frame_bytes)
            except PeerClosed:
                return
            try:
                reply = _handle(policy, message)
                if reply is None:
                    return
                frame = encode_frame(reply, max_frame_bytes=max_frame_bytes)
            except Exception as exc:  # the policy's own bug: report it, keep serving
                traceback.print_exc()
                frame = encode_frame(_error_reply(exc), max_frame_bytes=max_frame_bytes)
            sock.sendall(frame)
