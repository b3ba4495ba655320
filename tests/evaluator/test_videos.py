"""Episode videos in the evaluator: which episodes are recorded, their frames, their encoding.

A scripted stand-in for the ManiSkill environment makes the frame count exact and cheap; one
test encodes real frames with the bundled ffmpeg to check what browsers need.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from evaluator import runner
from evaluator.conditions import ConditionRuntime
from evaluator.episode import run_episode
from evaluator.job import EvaluationJob, evaluation_job
from evaluator.plan import TaskRun, build_plan
from evaluator.results import Video
from evaluator.runner import RunOptions, ShardOutcome, make_shards, run_units
from evaluator.suite import Condition, Nominal, Suite, SuiteError
from evaluator.video import VIDEO_NAME, video_name, write_video
from tests.evaluator.conftest import HERE, tiny_plan, tiny_suite

SIDE = 16  # pixels: enough for an encoder, cheap on a loaded machine


class ScriptedEnv:
    """Never ends by itself; each rendered frame's pixels hold the steps taken so far."""

    def __init__(self) -> None:
        self.steps = 0
        self.unwrapped = SimpleNamespace(
            _default_sim_config=SimpleNamespace(control_freq=20),
            control_freq=20,
            single_action_space=SimpleNamespace(low=-np.ones(2), high=np.ones(2)),
            single_observation_space=SimpleNamespace(shape=(3,), dtype="float32"),
        )

    def reset(self, seed: int) -> tuple[Any, dict[str, Any]]:
        self.steps = 0
        return np.zeros((1, 3), dtype=np.float32), {}

    def step(self, action: Any) -> tuple[Any, ...]:
        self.steps += 1
        obs = np.full((1, 3), self.steps, dtype=np.float32)
        return obs, np.zeros(1), np.zeros(1, bool), np.zeros(1, bool), {"success": np.zeros(1)}

    def render(self) -> Any:
        return np.full((1, SIDE, SIDE, 3), self.steps, dtype=np.uint8)

    def close(self) -> None:
        pass


class StillPolicy:
    """A PolicyChannel that answers every observation with a zero action."""

    policy_time_s = 0.0

    def start_task(self, spec: dict[str, Any]) -> None:
        pass

    def reset(self, obs: Any, info: dict[str, Any]) -> None:
        pass

    def act(self, obs: Any) -> Any:
        return np.zeros(2, dtype=np.float32)


def nominal() -> ConditionRuntime:
    return ConditionRuntime(Condition(name="nominal", params=Nominal()))


def test_a_recording_starts_with_the_reset_state_and_has_a_frame_after_every_step():
    frames: list[np.ndarray] = []
    result = run_episode(
        ScriptedEnv(),
        StillPolicy(),
        nominal(),
        index=0,
        seed=7,
        step_limit=17,
        bounds=(-np.ones(2, np.float32), np.ones(2, np.float32)),
        ignore_terminations=False,
        frames=frames,
    )
    assert result.steps == 17
    assert len(frames) == 18  # the reset state, then one per step
    assert [int(f[0, 0, 0]) for f in frames] == list(range(18))


def test_the_first_n_episodes_of_every_task_and_condition_are_recorded_across_shards(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    plan = tiny_plan(conditions=["nominal", "obs_noise"], episodes=3, videos=2)
    rendered: list[tuple[int, bool]] = []
    written: list[tuple[str, str, int, int]] = []

    def make_env(run: TaskRun, runtime: ConditionRuntime, *, render: bool) -> ScriptedEnv:
        rendered.append((plan.runs.index(run), render))
        return ScriptedEnv()

    def write(frames: list[Any], directory: Path, *, run: TaskRun, episode: int, fps: int):
        written.append((run.condition.name, run.env_id, episode, len(frames)))
        return Video(env_id=run.env_id, condition=run.condition.name, episode=episode, path="x")

    monkeypatch.setattr(runner, "make_env", make_env)
    monkeypatch.setattr(runner, "write_video", write)
    outcome = ShardOutcome()
    for shard in make_shards(plan, 2):  # episodes 0-1 in one shard, 2 in the other
        run_units(
            plan,
            StillPolicy(),
            shard.units,
            outcome,
            options=RunOptions(video_dir=tmp_path),
            on_episode=lambda _run, _episode: None,
        )
    expected = {
        (condition, env_id, episode, 12 + 1)
        for condition in ("nominal", "obs_noise")
        for env_id in ("PickCube-v1", "PushCube-v1")
        for episode in (0, 1)
    }
    assert set(written) == expected
    assert len(written) == len(expected)
    assert len(outcome.videos) == len(expected)
    # Only the shard holding recorded episodes renders: rendering is what costs.
    assert sorted(rendered) == sorted(
        [(i, True) for i in range(len(plan.runs))] + [(i, False) for i in range(len(plan.runs))]
    )


def test_nothing_is_recorded_without_a_video_directory(monkeypatch: pytest.MonkeyPatch):
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1, videos=1)
    renders: list[bool] = []
    monkeypatch.setattr(
        runner, "make_env", lambda _run, _rt, *, render: renders.append(render) or ScriptedEnv()
    )
    outcome = ShardOutcome()
    run_units(
        plan,
        StillPolicy(),
        make_shards(plan, 1)[0].units,
        outcome,
        options=RunOptions(),
        on_episode=lambda _run, _episode: None,
    )
    assert renders == [False]
    assert outcome.videos == []


def test_the_suite_decides_how_many_episodes_are_recorded_and_the_hash_ignores_it():
    suite = tiny_suite()
    assert suite.videos == 0
    assert tiny_plan().videos == 0
    recording = suite.model_copy(update={"videos": 2})
    assert recording.sha256() == suite.sha256()
    assert build_plan(recording, "dev").videos == 2
    assert build_plan(recording, "dev", videos=0).videos == 0
    assert build_plan(suite, "dev", record_video=True).videos == 1  # `manieval evaluate --video`
    assert build_plan(recording, "dev", record_video=True).videos == 2
    with pytest.raises(SuiteError, match="videos"):
        build_plan(suite, "dev", videos=-1)
    plan = tiny_plan(videos=1)
    assert plan.records(plan.runs[0], 0)
    assert not plan.records(plan.runs[0], 1)


def test_a_suite_may_record_some_conditions_only_and_must_name_real_ones():
    suite = tiny_suite().model_copy(update={"videos": 1, "video_conditions": ("nominal",)})
    assert suite.sha256() == tiny_suite().sha256()
    plan = build_plan(suite, "dev")
    recorded = {run.condition.name: plan.records(run, 0) for run in plan.runs}
    assert recorded["nominal"]
    assert not any(on for name, on in recorded.items() if name != "nominal")
    assert len(recorded) > 1  # the tiny suite has other conditions to leave out
    everything = build_plan(suite, "dev", record_video=True)  # `evaluate --video`: all
    assert all(everything.records(run, 0) for run in everything.runs)
    text = (HERE / "tiny_suite.yaml").read_text() + "video_conditions: [no_such]\n"
    with pytest.raises(ValueError, match="video_conditions names no condition"):
        Suite.model_validate(yaml.safe_load(text))


def test_a_kubernetes_job_rebuilds_the_plan_with_the_suites_videos():
    text = (HERE / "tiny_suite.yaml").read_text() + "videos: 1\nvideo_conditions: [nominal]\n"
    plan = build_plan(Suite.model_validate(yaml.safe_load(text)), "dev", episodes=2)
    job = evaluation_job(plan, suite_yaml=text)
    assert EvaluationJob.model_validate_json(job.canonical_json()).plan() == plan
    assert (plan.videos, plan.video_conditions) == (1, ("nominal",))


def test_video_names_are_derived_from_the_run_and_refuse_anything_else():
    name = video_name(condition="obs_noise", env_id="PickCube-v1", episode=3)
    assert name == "obs_noise--PickCube-v1--ep3.mp4"
    assert VIDEO_NAME.match(name)
    for condition, env_id in (("../x", "PickCube-v1"), ("nominal", "a/b-v1"), ("n", "x")):
        with pytest.raises(ValueError, match="no video name"):
            video_name(condition=condition, env_id=env_id, episode=0)
    for bad in ("../nominal--PickCube-v1--ep0.mp4", "nominal--PickCube-v1--ep0.mp4.sh", ""):
        assert not VIDEO_NAME.match(bad)


def test_videos_are_h264_yuv420p_with_the_index_first_as_browsers_need(tmp_path: Path):
    import imageio.v2 as imageio
    import imageio_ffmpeg

    run = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1).runs[0]
    frames = [np.full((SIDE * 4, SIDE * 4, 3), 10 * i, dtype=np.uint8) for i in range(18)]
    video = write_video(frames, tmp_path, run=run, episode=0, fps=20)
    path = Path(video.path)
    assert path.name == "nominal--PickCube-v1--ep0.mp4"
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no partial file left
    data = path.read_bytes()
    assert data[4:8] == b"ftyp"
    assert 0 <= data.index(b"moov") < data.index(b"mdat")  # +faststart
    probe = subprocess.run(
        [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert "Video: h264" in probe.stderr, probe.stderr
    assert "yuv420p" in probe.stderr, probe.stderr
    assert len(imageio.mimread(path)) == 18
