"""Trajectory parts as a shard writes them (`evaluator.trajectory.TrajectoryRecorder`), small
and made without the simulator: for the tests of merging them."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from evaluator.trajectory import EPISODE_KEY, PARTS


def write_part(directory: Path, stem: str, *, first: int, episodes: int, steps: int = 3) -> None:
    """The part of task run `stem` holding episodes `first .. first+episodes-1` (its own
    `traj_0..`, as ManiSkill numbers a file's episodes); episode k's actions are all k."""
    parts = directory / PARTS
    parts.mkdir(parents=True, exist_ok=True)
    path = parts / f"{stem}--from{first:06d}.h5"
    meta: dict = {"env_info": {"env_id": stem.split("--")[1]}, "episodes": []}
    with h5py.File(path, "w") as f:
        for own in range(episodes):
            index = first + own
            traj = f.create_group(f"traj_{own}")
            traj.create_dataset("actions", data=np.full((steps, 7), index, dtype=np.float32))
            meta["episodes"].append(
                {"episode_id": own, "reset_kwargs": {"seed": 1000 + index}, EPISODE_KEY: index}
            )
    path.with_suffix(".json").write_text(json.dumps(meta), encoding="utf-8")


def episode_indices(h5: Path) -> list[int]:
    """Which task-run episode each episode of a merged file is, in its order (from the JSON),
    checked against the file's `traj_0..` and, for parts `write_part` made, their actions."""
    meta = json.loads(h5.with_suffix(".json").read_text(encoding="utf-8"))
    indices = [e[EPISODE_KEY] for e in meta["episodes"]]
    assert [e["episode_id"] for e in meta["episodes"]] == list(range(len(indices)))
    with h5py.File(h5, "r") as f:
        assert sorted(f) == sorted(f"traj_{n}" for n in range(len(indices)))
        if meta["env_info"].keys() == {"env_id"}:  # made by write_part
            assert [int(f[f"traj_{n}"]["actions"][0, 0]) for n in range(len(indices))] == indices
    return indices
