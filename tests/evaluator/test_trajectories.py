"""Trajectories in ManiSkill's format: what is recorded, that ManiSkill's replay tool gets every
episode's success back, and that neither sharding nor recording changes anything."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EvaluationResult, episode_records
from evaluator.sources import LocalDirectory
from evaluator.suite import Suite
from evaluator.trajectory import (
    EPISODE_KEY,
    PARTS,
    TRAJECTORY_NAME,
    TrajectoryRecorder,
    merge_parts,
    trajectory_stem,
)
from testkit.trajectories import episode_indices, write_part
from tests.evaluator.conftest import HERE, SCRIPTED

# PickCube in 20 steps: the scripted policy succeeds on two of these three seeds, so replay
# has both outcomes to get back; low_freq changes the environment's own arguments.
SUITE = (
    (HERE / "tiny_suite.yaml").read_text().replace("max_episode_steps: 12", "max_episode_steps: 20")
)


def plan() -> EvaluationPlan:
    suite = Suite.model_validate(yaml.safe_load(SUITE))
    return build_plan(suite, "dev", conditions=["nominal", "low_freq"])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[EvaluationResult, Path]:
    directory = tmp_path_factory.mktemp("trajectories")
    result = evaluate(plan(), LocalDirectory(SCRIPTED), trajectory_dir=directory)
    return result, directory


def episodes_of(result: EvaluationResult, condition: str, env_id: str) -> list:
    return next(
        t.episodes
        for c in result.conditions
        if c.name == condition
        for t in c.tasks
        if t.env_id == env_id
    )


def test_every_task_run_gets_one_h5_and_one_json_and_no_parts_are_left(recorded):
    result, directory = recorded
    stems = {
        trajectory_stem(condition=c.name, env_id=t.env_id)
        for c in result.conditions
        for t in c.tasks
    }
    names = {p.name for p in directory.iterdir()}
    assert names == {f"{s}.{ext}" for s in stems for ext in ("h5", "json")}
    assert all(TRAJECTORY_NAME.match(name) for name in names)
    assert not (directory / PARTS).exists()


def test_h5py_reads_the_keys_maniskill_documents_and_the_json_says_how_to_replay(recorded):
    result, directory = recorded
    stem = trajectory_stem(condition="low_freq", env_id="PickCube-v1")
    meta = json.loads((directory / f"{stem}.json").read_text())
    assert meta["env_info"]["env_id"] == "PickCube-v1"
    kwargs = meta["env_info"]["env_kwargs"]
    assert kwargs["control_mode"] == "pd_ee_delta_pose"
    assert kwargs["sim_config"] == {"control_freq": 5}
    episodes = episodes_of(result, "low_freq", "PickCube-v1")
    assert [e["reset_kwargs"]["seed"] for e in meta["episodes"]] == [e.seed for e in episodes]
    assert [e[EPISODE_KEY] for e in meta["episodes"]] == [e.index for e in episodes]
    with h5py.File(directory / f"{stem}.h5", "r") as f:
        assert sorted(f) == [f"traj_{i}" for i in range(len(episodes))]
        for i, episode in enumerate(episodes):
            traj = f[f"traj_{i}"]
            assert {"actions", "env_states", "success", "terminated", "truncated"} <= set(traj)
            assert traj["actions"].shape == (episode.steps, 7)
            assert traj["actions"].dtype == np.float32
            assert traj["success"].shape == (episode.steps,)
            assert traj["env_states"]["articulations"]["panda"].shape[0] == episode.steps + 1
            assert meta["episodes"][i]["elapsed_steps"] == episode.steps


def test_maniskills_replay_tool_gets_every_episodes_success_back(recorded, tmp_path: Path):
    result, directory = recorded
    successes = []
    for condition, env_id in [("nominal", "PickCube-v1"), ("low_freq", "PushCube-v1")]:
        stem = trajectory_stem(condition=condition, env_id=env_id)
        copy = tmp_path / f"{stem}.h5"  # the replay writes beside the file it reads
        copy.write_bytes((directory / f"{stem}.h5").read_bytes())
        copy.with_suffix(".json").write_bytes((directory / f"{stem}.json").read_bytes())
        subprocess.run(
            [
                sys.executable,
                "-m",
                "mani_skill.trajectory.replay_trajectory",
                "--traj-path",
                str(copy),
                "--save-traj",
                "--allow-failure",
            ],
            check=True,
            capture_output=True,
            timeout=600,
        )
        (replayed,) = tmp_path.glob(f"{stem}.*.json")
        meta = json.loads(replayed.read_text())
        replay = [bool(e["success"]) for e in meta["episodes"]]
        expected = [e.success_once for e in episodes_of(result, condition, env_id)]
        assert replay == expected
        successes += replay
    assert True in successes  # both outcomes were replayed
    assert False in successes


def test_sharded_and_unsharded_files_hold_the_same_episodes_in_the_same_order(
    recorded, tmp_path: Path
):
    result, directory = recorded
    sharded = evaluate(plan(), LocalDirectory(SCRIPTED), workers=2, trajectory_dir=tmp_path)
    assert episode_records(sharded) == episode_records(result)
    for h5 in sorted(directory.glob("*.h5")):
        one = json.loads(h5.with_suffix(".json").read_text())["episodes"]
        two = json.loads((tmp_path / h5.with_suffix(".json").name).read_text())["episodes"]
        assert one == two
        with h5py.File(h5, "r") as a, h5py.File(tmp_path / h5.name, "r") as b:
            assert list(a) == list(b)
            for name in a:
                np.testing.assert_array_equal(a[name]["actions"][:], b[name]["actions"][:])
                np.testing.assert_array_equal(
                    a[name]["env_states"]["actors"]["cube"][:],
                    b[name]["env_states"]["actors"]["cube"][:],
                )


def test_recording_changes_no_episode(recorded):
    result, _ = recorded
    plain = evaluate(plan(), LocalDirectory(SCRIPTED))
    assert episode_records(plain) == episode_records(result)
    assert plain.score == result.score


def test_no_trajectory_directory_records_nothing(monkeypatch: pytest.MonkeyPatch):
    def refuse(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("recorded without a trajectory directory")

    monkeypatch.setattr(TrajectoryRecorder, "wrap", refuse)
    suite = Suite.model_validate(yaml.safe_load(SUITE))
    small = build_plan(suite, "dev", tasks=["PushCube-v1"], conditions=["nominal"], episodes=1)
    evaluate(small, LocalDirectory(SCRIPTED))


def test_trajectory_names_are_derived_from_the_run_and_refuse_anything_else():
    assert trajectory_stem(condition="nominal", env_id="PickCube-v1") == "nominal--PickCube-v1"
    for condition, env_id in [("../x", "PickCube-v1"), ("nominal", "a/b-v1"), ("n", "NoVersion")]:
        with pytest.raises(ValueError, match="no trajectory name"):
            trajectory_stem(condition=condition, env_id=env_id)


def test_a_policy_that_breaks_before_its_first_episode_leaves_no_trajectory_and_no_error(
    make_policy: Callable[[str], Path], tmp_path: Path
):
    """Nothing ran, so nothing is recorded: the evaluation ends as the policy's failure, never
    as the recorder's (a part with no episode has no JSON to mark)."""
    crasher = make_policy("import sys\nsys.exit(3)\n")
    directory = tmp_path / "recorded"
    result = evaluate(plan(), LocalDirectory(crasher), trajectory_dir=directory)
    assert result.status == "aborted"
    assert result.abort is not None
    assert result.abort.kind == "policy_crashed"
    assert not list(directory.rglob("*.h5"))
    assert not list(directory.rglob("*.json"))


def test_parts_merge_in_episode_order_and_a_repeated_merge_changes_nothing(tmp_path: Path):
    stem = trajectory_stem(condition="nominal", env_id="PickCube-v1")
    write_part(tmp_path, stem, first=2, episodes=1)  # written first, merged last
    write_part(tmp_path, stem, first=0, episodes=2)
    assert merge_parts(tmp_path, [stem, "nominal--PushCube-v1"]) == [tmp_path / f"{stem}.h5"]
    assert episode_indices(tmp_path / f"{stem}.h5") == [0, 1, 2]
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{stem}.h5", f"{stem}.json"]
    before = (tmp_path / f"{stem}.json").read_bytes()
    assert merge_parts(tmp_path, [stem]) == []
    assert (tmp_path / f"{stem}.json").read_bytes() == before


def test_a_merge_cut_short_after_its_files_appeared_only_removes_the_leftover_parts(
    tmp_path: Path,
):
    """The merged files appear whole or not at all; once there, the parts they were made of are
    only removed, so a merge repeated after a crash never writes a file of fewer episodes."""
    stem = trajectory_stem(condition="nominal", env_id="PickCube-v1")
    write_part(tmp_path, stem, first=0, episodes=2)
    write_part(tmp_path, stem, first=2, episodes=2)
    merge_parts(tmp_path, [stem])
    write_part(tmp_path, stem, first=2, episodes=2)  # the crash left this part behind
    merge_parts(tmp_path, [stem])
    assert episode_indices(tmp_path / f"{stem}.h5") == [0, 1, 2, 3]
    assert not (tmp_path / PARTS).exists()
