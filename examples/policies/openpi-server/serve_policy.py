"""An openpi-protocol policy server: the stand-in for a participant's model server (openpi's
scripts/serve_policy.py serves pi0 the same way). Its policy acts on what its camera sees: it
finds the red pixels of the image (PickCube's cube is red) and moves the gripper so that they
come to the image's centre, eight steps per inference. It scores little; it shows the path.

    python3 serve_policy.py --port 8000 [--fail-on-call N]

--fail-on-call N makes the Nth inference raise, to show how a server's error reaches you.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

import numpy as np

IMAGE_SIZE = (96, 96)  # what the model takes: the bridge resizes the camera's 128 px to this
ACTION_HORIZON = 8
ACTION_DIM = 8  # the model's action width: the Panda's 7, padded as openpi's models pad theirs
GRIPPER_OPEN = 1.0
GAIN = 0.5
METADATA = {
    "policy": "red-seeker",
    "image_resolution": list(IMAGE_SIZE),
    "action_horizon": ACTION_HORIZON,
    "action_dim": ACTION_DIM,
}


class RedSeeker:
    """Moves the gripper towards the red pixels of the image it is given."""

    def __init__(self, *, fail_on_call: int | None = None) -> None:
        self.fail_on_call = fail_on_call
        self.calls = 0

    def infer(self, obs: dict[str, Any]) -> dict[str, Any]:
        self.calls += 1
        if self.calls == self.fail_on_call:
            raise RuntimeError(f"inference {self.calls} fails, as --fail-on-call asked")
        image = _entry(obs, "observation/image", np.uint8, (*IMAGE_SIZE, 3))
        _entry(obs, "observation/state", np.float32, None)  # a model would condition on it
        prompt = obs.get("prompt")
        if not isinstance(prompt, str) or not prompt:
            raise ValueError(f"the request's prompt must be a non-empty string, not {prompt!r}")
        rgb = image.astype(np.int32)
        red = (
            (rgb[..., 0] > 100)
            & (rgb[..., 0] > rgb[..., 1] + 40)
            & (rgb[..., 0] > rgb[..., 2] + 40)
        )
        action = np.zeros(ACTION_DIM, dtype=np.float32)
        action[6] = GRIPPER_OPEN
        if red.any():
            rows, cols = np.nonzero(red)
            offset_down = rows.mean() / IMAGE_SIZE[0] * 2 - 1  # -1 at the top, 1 at the bottom
            offset_right = cols.mean() / IMAGE_SIZE[1] * 2 - 1
            action[0] = -GAIN * offset_down
            action[1] = -GAIN * offset_right
        return {"actions": np.tile(action, (ACTION_HORIZON, 1))}


def _entry(obs: dict[str, Any], key: str, dtype: Any, shape: tuple[int, ...] | None) -> np.ndarray:
    value = obs.get(key)
    if not isinstance(value, np.ndarray):
        raise ValueError(f"the request has no array {key!r} (it has: {', '.join(sorted(obs))})")
    if value.dtype != dtype or (shape is not None and value.shape != shape):
        want = f"{np.dtype(dtype)} {list(shape) if shape else '[N]'}"
        raise ValueError(f"{key} is {value.dtype} {list(value.shape)}, the model takes {want}")
    return value


def main() -> None:
    # Here, not above: the policy itself needs numpy alone (ManiEval's tests import it without
    # websockets, to run it in-process beside its served self).
    from websocket_policy_server import WebsocketPolicyServer

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--fail-on-call", type=int, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="policy-server: %(message)s")
    policy = RedSeeker(fail_on_call=args.fail_on_call)
    server = WebsocketPolicyServer(policy, host=args.host, port=args.port, metadata=METADATA)
    server.serve_forever()


if __name__ == "__main__":
    main()
