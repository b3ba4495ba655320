"""Episode trajectories in ManiSkill's own format: `<name>.h5` + `<name>.json`, one pair per
task run, as `mani_skill.utils.wrappers.RecordEpisode` writes them and
`python -m mani_skill.trajectory.replay_trajectory` replays them (docs/trajectories.md).

ManiSkill's wrapper records every step the simulator takes (the action applied, after
clipping, and the env state after it), with no rendering. Each shard writes a part per task
run; `merge_parts` joins a task run's parts as ManiSkill's `merge_trajectories` does, in
episode order, so the merged file is the same however the episodes were sharded.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from evaluator.plan import EvaluationPlan, TaskRun

TRAJECTORY_NAME = re.compile(r"^[a-z0-9_\-]{1,100}--[A-Za-z0-9_\-]{1,100}-v\d{1,6}\.(h5|json)\Z")
"""What a stored trajectory file's name looks like: derived from its run, never from input."""
PARTS = "parts"
EPISODE_KEY = "manieval_episode"
"""The key each episode of the JSON gets beside ManiSkill's own: its index in its task run."""
SOURCE_TYPE = "manieval"


def trajectory_stem(*, condition: str, env_id: str) -> str:
    """A task run's trajectory files are `<stem>.h5` and `<stem>.json` (ValueError if the
    parts are not names)."""
    stem = f"{condition}--{env_id}"
    if not TRAJECTORY_NAME.match(f"{stem}.h5"):
        raise ValueError(f"no trajectory name for {condition!r}, {env_id!r}")
    return stem


def run_stem(run: TaskRun) -> str:
    """The stem of a task run's trajectory files."""
    return trajectory_stem(condition=run.condition.name, env_id=run.env_id)


class TrajectoryRecorder:
    """Records a task run's episodes (some of them: a shard's) with ManiSkill's RecordEpisode.

    `wrap` puts the wrapper around the environment; `episode_done` writes the episode that just
    ran; `close` finishes the part and marks each episode with its index in the task run."""

    def __init__(self, directory: Path, *, run: TaskRun, first_episode: int) -> None:
        self._path = directory / PARTS / f"{run_stem(run)}--from{first_episode:06d}.h5"
        self._run = run
        self._indices: list[int] = []
        self._wrapper: Any = None

    def wrap(self, env: Any) -> Any:
        """`env`, recorded: every step's applied action and env state, no frames."""
        from mani_skill.utils.wrappers.record import RecordEpisode

        self._path.parent.mkdir(parents=True, exist_ok=True)
        self._wrapper = RecordEpisode(
            env,
            output_dir=str(self._path.parent),
            trajectory_name=self._path.stem,
            save_trajectory=True,
            save_video=False,
            save_on_reset=False,  # each episode is written when it ends (`episode_done`)
            clean_on_close=False,
            record_reward=False,  # rewards are deferred (evaluator.sim); replay recomputes them
            source_type=SOURCE_TYPE,
            source_desc=f"condition {self._run.condition.name}: "
            f"{self._run.condition.params.model_dump_json()}",
        )
        return self._wrapper

    def episode_done(self, index: int) -> None:
        """Write the episode just run (reset, then its steps; none is left out)."""
        self._wrapper.flush_trajectory(ignore_empty_transition=False)
        self._indices.append(index)

    def close(self) -> None:
        """Close the part's file and mark its episodes with their index in the task run; a
        part no episode was written to (the policy broke before its first) is removed: it
        has nothing to replay, and its absence must not fail the evaluation."""
        if self._wrapper is not None:
            self._wrapper.close()
        json_path = self._path.with_suffix(".json")
        if not self._indices:
            self._path.unlink(missing_ok=True)
            json_path.unlink(missing_ok=True)
            return
        document = json.loads(json_path.read_text(encoding="utf-8"))
        episodes = document["episodes"]
        if len(episodes) != len(self._indices):
            raise RuntimeError(f"{json_path} has {len(episodes)} episodes, {self._indices} ran")
        for episode, index in zip(episodes, self._indices, strict=True):
            episode[EPISODE_KEY] = index
        json_path.write_text(json.dumps(document, indent=2), encoding="utf-8")


def merge_parts(directory: Path, stems: Iterable[str]) -> list[Path]:
    """Merge each task run's parts (named by its stem) into `<directory>/<stem>.h5` (+ `.json`),
    episodes in task-run order, and remove the parts; the merged files' paths (runs without
    parts have none).

    Safe to repeat after a crash: a task run's files appear whole (written aside, then renamed,
    the `.h5` last), and a run whose `.h5` is there is merged already, so its leftover parts are
    only removed. That is what lets the server merge the parts Kubernetes pods leave on the
    video volume when the attempt's final report comes, and again if the report is resent."""
    merged = []
    for stem in stems:
        parts = _parts_of(directory / PARTS, stem)
        target = directory / f"{stem}.h5"
        if parts and not target.is_file():
            _merge(target, parts)
        for part in parts:
            part.unlink()
            part.with_suffix(".json").unlink()
        if parts:
            merged.append(target)
    _remove_if_empty(directory / PARTS)
    return merged


def plan_stems(plan: EvaluationPlan) -> list[str]:
    """The stems of a plan's task runs, in plan order."""
    return [run_stem(run) for run in plan.runs]


def _merge(target: Path, parts: Sequence[Path]) -> None:
    """Write the parts' episodes into `target` (+ `.json`) as ManiSkill's `merge_trajectories`
    does (`mani_skill/trajectory/merge_trajectory.py`: the first part's keys, then every part's
    episodes renumbered `traj_0..`), with h5py alone: importing ManiSkill's module loads the
    simulator and torch, which the server, where Kubernetes attempts are merged, never loads."""
    import h5py

    document: dict[str, Any] = {"episodes": []}
    aside = target.with_name(f".{target.name}.merging")
    with h5py.File(aside, "w") as out:
        for part in parts:
            meta = json.loads(part.with_suffix(".json").read_text(encoding="utf-8"))
            for key, value in meta.items():
                document.setdefault(key, value)
            with h5py.File(part, "r") as source:
                for episode in meta["episodes"]:
                    number = len(document["episodes"])
                    source.copy(f"traj_{episode['episode_id']}", out, f"traj_{number}")
                    document["episodes"].append({**episode, "episode_id": number})
    json_aside = aside.with_suffix(".json.merging")
    json_aside.write_text(json.dumps(document, indent=2), encoding="utf-8")
    os.replace(json_aside, target.with_suffix(".json"))
    os.replace(aside, target)


def _parts_of(parts: Path, stem: str) -> Sequence[Path]:
    """A task run's parts in episode order (their names carry their first episode's index,
    zero-padded: name order is episode order)."""
    if not parts.is_dir():
        return []
    return sorted(p for p in parts.glob(f"{stem}--from*.h5") if p.with_suffix(".json").is_file())


def _remove_if_empty(directory: Path) -> None:
    if directory.is_dir() and not any(directory.iterdir()):
        directory.rmdir()
