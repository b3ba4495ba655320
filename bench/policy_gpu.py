"""A neural policy on a GPU against the same policy on the CPU, through the wire protocol.

The policy (bench/torch_policy: a ResNet-18 encoder of an RGB-D frame and an MLP head that
predicts 8 actions) runs in its own process, as in a policy container, and answers `act` calls
over the protocol with observations shaped like the visual suite's (`rgbd`, one camera). Each
row prints the median and 95th percentile milliseconds of a whole `act` call as the evaluator
sees it (sending the observation, the network, the reply) on each device, the two devices
taking turns call by call so that what else the machine does hits both alike. The last line
is `policy_gpu_speedup <cpu ms / gpu ms at 128 px>`; without a GPU it says so and measures the
CPU alone.

    .venv/bin/python bench/policy_gpu.py [--calls 200] [--sizes 128,224]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "evaluator" / "sdk"))

from evaluator.endpoint import PolicyEndpoint  # noqa: E402

POLICY = Path(__file__).parent / "torch_policy" / "policy.py"
QPOS = 9
ACTION = 7


def spec(size: int) -> dict[str, Any]:
    """A task spec with the visual suite's observation structure at `size` pixels."""
    leaf = lambda shape, dtype: {"shape": list(shape), "dtype": dtype}  # noqa: E731
    return {
        "env_id": "PickCube-v1",
        "obs_mode": "rgbd",
        "control_mode": "pd_ee_delta_pose",
        "control_freq": 20,
        "max_episode_steps": 100,
        "action_space": {
            "low": -np.ones(ACTION, np.float32),
            "high": np.ones(ACTION, np.float32),
        },
        "observation_space": {
            "agent": {"qpos": leaf([QPOS], "float32"), "qvel": leaf([QPOS], "float32")},
            "sensor_data": {
                "base_camera": {
                    "rgb": leaf([size, size, 3], "uint8"),
                    "depth": leaf([size, size, 1], "int16"),
                }
            },
        },
    }


def observation(rng: np.random.Generator, size: int) -> dict[str, Any]:
    return {
        "agent": {
            "qpos": rng.standard_normal(QPOS).astype(np.float32),
            "qvel": rng.standard_normal(QPOS).astype(np.float32),
        },
        "sensor_data": {
            "base_camera": {
                "rgb": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
                "depth": rng.integers(0, 2000, (size, size, 1), dtype=np.int16),
            }
        },
    }


class Served:
    """The policy in its own process on `device`, connected and set up for a task."""

    def __init__(self, device: str, task: dict[str, Any]) -> None:
        self.endpoint = PolicyEndpoint(max_frame_bytes=1 << 20)
        env = os.environ | {
            "MANIEVAL_ENDPOINT": self.endpoint.address,
            "POLICY_DEVICE": device,
            "PYTHONPATH": str(REPO / "evaluator" / "sdk"),
        }
        self.process = subprocess.Popen([sys.executable, str(POLICY)], env=env)
        self.endpoint.accept(timeout=120, alive=lambda: self.process.poll() is None)
        self.endpoint.hello(timeout=120)
        self.endpoint.call({"type": "task", "spec": task}, expect="ok", timeout=300)

    def act(self, obs: dict[str, Any]) -> float:
        """Milliseconds of one `act` call, as the evaluator sees it."""
        started = time.perf_counter()
        action = self.endpoint.act(obs, timeout=120)
        elapsed = (time.perf_counter() - started) * 1000
        assert isinstance(action, np.ndarray), action
        assert action.shape[-1] == ACTION, action.shape
        return elapsed

    def close(self) -> None:
        self.endpoint.close()
        self.process.terminate()
        self.process.wait(timeout=30)


def measure(devices: list[str], size: int, calls: int) -> dict[str, list[float]]:
    """Each device's `act` milliseconds, the devices taking turns call by call."""
    task = spec(size)
    served = [Served(device, task) for device in devices]
    try:
        rng = np.random.default_rng(size)
        for policy in served:  # warm up: kernels chosen, caches filled
            for _ in range(10):
                policy.act(observation(rng, size))
        times: dict[str, list[float]] = {device: [] for device in devices}
        for n in range(calls):
            obs = observation(rng, size)
            order = served if n % 2 == 0 else served[::-1]
            for policy, device in ((p, devices[served.index(p)]) for p in order):
                times[device].append(policy.act(obs))
        return times
    finally:
        for policy in served:
            policy.close()


def gpu_name() -> str | None:
    """The GPU torch sees, or None."""
    probe = (
        "import torch; print(torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
    )
    name = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True
    ).stdout.strip()
    return name or None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--sizes", default="128,224")
    args = parser.parse_args()
    gpu = gpu_name()
    devices = ["cpu", "cuda"] if gpu else ["cpu"]
    print(f"GPU: {gpu or 'none (the CPU alone is measured)'}; CPU cores: {os.cpu_count()}")
    print(f"{'pixels':<8}{'device':<8}{'median ms':>10}{'p95 ms':>9}")
    speedup = None
    for size in (int(s) for s in args.sizes.split(",")):
        times = measure(devices, size, args.calls)
        for device, ms in times.items():
            p95 = statistics.quantiles(ms, n=20)[-1]
            print(f"{size:<8}{device:<8}{statistics.median(ms):>10.2f}{p95:>9.2f}")
        if gpu and speedup is None:
            speedup = statistics.median(times["cpu"]) / statistics.median(times["cuda"])
    if speedup is None:
        print("policy_gpu_speedup n/a (no GPU)")
    else:
        print(f"policy_gpu_speedup {speedup:.1f}")


if __name__ == "__main__":
    main()
