"""Episode videos in the evaluator: which episodes are recorded, their frames, their encoding.

A scripted stand-in for the ManiSkill environment makes the frame count exact and cheap; one
test encodes real frames with the bundled ffmpeg to check what browsers need.
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from evaluator import runner
from evaluator.conditions import ConditionRuntime
from evaluator.endpoint import PolicyRaised
from evaluator.episode import run_episode
from evaluator.job import EvaluationJob, evaluation_job
from evaluator.plan import TaskRun, build_plan
from evaluator.results import Video
from evaluator.runner import RunOptions, ShardOutcome, make_shards, run_units
from evaluator.suite import Condition, Nominal, Suite, SuiteError
from evaluator.video import POSTER_MAX_SIDE, VIDEO_NAME, poster_name, video_name, write_video
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

    def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
        return {"action": np.zeros(2, dtype=np.float32)}


def nominal() -> ConditionRuntime:
    return ConditionRuntime(Condition(name="nominal", params=Nominal()))


def film(policy: Any, *, every: int = 1, step_limit: int = 17) -> tuple[Any, list[np.ndarray]]:
    """An episode of the scripted environment, filmed every `every` steps: result, frames."""
    frames: list[np.ndarray] = []
    result = run_episode(
        ScriptedEnv(),
        policy,
        nominal(),
        index=0,
        seed=7,
        step_limit=step_limit,
        bounds=(-np.ones(2, np.float32), np.ones(2, np.float32)),
        ignore_terminations=False,
        frames=frames,
        frame_every=every,
    )
    return result, frames


def test_a_recording_starts_with_the_reset_state_and_has_a_frame_after_every_step():
    result, frames = film(StillPolicy())
    assert result.steps == 17
    assert len(frames) == 18  # the reset state, then one per step
    assert [int(f[0, 0, 0]) for f in frames] == list(range(18))


@pytest.mark.parametrize(
    ("every", "filmed"), [(3, [0, 3, 6, 9, 12, 15, 17]), (17, [0, 17]), (20, [0, 17])]
)
def test_a_film_at_a_lower_rate_keeps_every_kth_step_and_always_the_last(
    every: int, filmed: list[int]
):
    _, frames = film(StillPolicy(), every=every)
    assert [int(f[0, 0, 0]) for f in frames] == filmed


def test_a_policy_that_raises_is_filmed_to_the_state_it_left():
    class RaisesAtStep5(StillPolicy):
        calls = 0

        def act(self, obs: Any, *, meanwhile: Callable[[], None] = lambda: None) -> dict[str, Any]:
            self.calls += 1
            if self.calls == 6:
                raise PolicyRaised("ValueError: no")
            return super().act(obs)

    result, frames = film(RaisesAtStep5(), every=4)
    assert (result.failure, result.steps) == ("policy_error", 5)
    assert [int(f[0, 0, 0]) for f in frames] == [0, 4, 5]


def test_a_rate_limit_films_every_kth_step_and_plays_in_real_time(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    suite = tiny_suite().model_copy(update={"videos": 1, "video_size": 64, "video_fps": 8})
    plan = build_plan(suite, "dev", tasks=["PickCube-v1"], conditions=["nominal"], episodes=1)
    sizes: list[int | None] = []
    written: list[tuple[int, float]] = []

    def make_env(_run: TaskRun, _rt: ConditionRuntime, *, render: bool, frame_size: int | None):
        sizes.append(frame_size)
        return ScriptedEnv()

    def write(frames: list[Any], directory: Path, *, run: TaskRun, episode: int, fps: float):
        written.append((len(frames), fps))
        return Video(env_id=run.env_id, condition=run.condition.name, episode=episode, path="x")

    monkeypatch.setattr(runner, "make_env", make_env)
    monkeypatch.setattr(runner, "write_video", write)
    run_units(
        plan,
        StillPolicy(),
        make_shards(plan, 1)[0].units,
        ShardOutcome(),
        options=RunOptions(video_dir=tmp_path),
        on_episode=lambda _run, _episode: None,
    )
    assert sizes == [64]
    steps = plan.runs[0].max_episode_steps  # the scripted environment never ends by itself
    # 20 Hz control at most 8 frames a second: every 3rd step, played at 20/3 frames a second.
    assert written == [(1 + steps // 3 + (steps % 3 > 0), 20 / 3)]


def test_the_frame_stride_keeps_within_the_suites_rate():
    plan = tiny_plan()
    assert plan.video_fps is None
    assert plan.frame_stride(20) == 1
    for fps, control, stride in [(10, 20, 2), (15, 20, 2), (20, 20, 1), (10, 5, 1), (7, 30, 5)]:
        assert plan.model_copy(update={"video_fps": fps}).frame_stride(control) == stride


def test_the_first_n_episodes_of_every_task_and_condition_are_recorded_across_shards(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    plan = tiny_plan(conditions=["nominal", "obs_noise"], episodes=3, videos=2)
    rendered: list[tuple[int, bool]] = []
    written: list[tuple[str, str, int, int]] = []

    def make_env(
        run: TaskRun, runtime: ConditionRuntime, *, render: bool, frame_size: int | None
    ) -> ScriptedEnv:
        rendered.append((plan.runs.index(run), render))
        return ScriptedEnv()

    def write(frames: list[Any], directory: Path, *, run: TaskRun, episode: int, fps: float):
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
        runner,
        "make_env",
        lambda _run, _rt, *, render, frame_size: renders.append(render) or ScriptedEnv(),
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


def test_a_suite_sets_the_frames_size_and_rate_outside_the_hash():
    text = (HERE / "tiny_suite.yaml").read_text()
    suite = Suite.model_validate(yaml.safe_load(text + "video_size: 256\nvideo_fps: 10\n"))
    assert suite.sha256() == tiny_suite().sha256()
    plan = build_plan(suite, "dev")
    assert (plan.video_size, plan.video_fps) == (256, 10)
    for bad, message in [
        ("video_size: 100", "multiple of 16"),
        ("video_size: 32", "greater than or equal to 64"),
        ("video_size: 4096", "less than or equal to 2048"),
        ("video_fps: 0", "greater than or equal to 1"),
        ("video_size: big", "valid integer"),
    ]:
        with pytest.raises(ValueError, match=message):
            Suite.model_validate(yaml.safe_load(f"{text}{bad}\n"))


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
    text = (HERE / "tiny_suite.yaml").read_text() + (
        "videos: 1\nvideo_conditions: [nominal]\nvideo_size: 128\nvideo_fps: 10\n"
    )
    plan = build_plan(Suite.model_validate(yaml.safe_load(text)), "dev", episodes=2)
    job = evaluation_job(plan, suite_yaml=text)
    assert EvaluationJob.model_validate_json(job.canonical_json()).plan() == plan
    assert (plan.videos, plan.video_conditions) == (1, ("nominal",))
    assert (plan.video_size, plan.video_fps) == (128, 10)


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
    video = write_video(frames, tmp_path, run=run, episode=0, fps=20 / 3)  # 20 Hz, every 3rd
    path = Path(video.path)
    assert path.name == "nominal--PickCube-v1--ep0.mp4"
    left = sorted(p.name for p in tmp_path.iterdir())  # no partial file left
    assert left == [path.name, poster_name(path.name)]
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
    assert "6.67 fps" in probe.stderr, probe.stderr  # real time, whatever the stride
    assert len(imageio.mimread(path)) == 18


def test_the_evaluator_keeps_the_first_frame_beside_the_video_as_its_poster(tmp_path: Path):
    """What a page shows before the video plays, made where the frames are: no server needs
    a decoder for it. It carries the video's modification time, which makes it that video's."""
    from PIL import Image

    run = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1).runs[0]
    first = np.zeros((768, 1024, 3), dtype=np.uint8)
    first[..., 0] = 200  # red: the reset state
    frames = [first, *(np.full((768, 1024, 3), 30, dtype=np.uint8) for _ in range(3))]
    path = Path(write_video(frames, tmp_path, run=run, episode=0, fps=10).path)
    poster = tmp_path / poster_name(path.name)
    assert poster.name == "nominal--PickCube-v1--ep0.poster.jpg"
    assert poster.stat().st_mtime_ns == path.stat().st_mtime_ns
    with Image.open(poster) as image:
        assert image.format == "JPEG"
        assert image.size == (POSTER_MAX_SIDE, POSTER_MAX_SIDE * 768 // 1024)  # its shape kept
        red, green, blue = image.convert("RGB").getpixel((10, 10))  # type: ignore[misc]
    assert (red > 150, green < 60, blue < 60) == (True, True, True)  # the first frame


def test_a_real_task_renders_frames_of_the_suites_size():
    from evaluator.sim import make_env, to_numpy

    run = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=1).runs[0]
    for size in (64, None):  # None: the task's own camera, 512 pixels for PickCube-v1
        env = make_env(run, nominal(), render=True, frame_size=size)
        try:
            env.reset(seed=0)
            frame = to_numpy(env.render())
        finally:
            env.close()
        side = size or 512
        assert (frame.shape, frame.dtype) == ((side, side, 3), np.uint8)
        assert frame.std() > 0  # a scene, not a blank


def test_a_film_needs_a_positive_stride():
    with pytest.raises(ValueError, match="frame_every must be at least 1"):
        film(StillPolicy(), every=0, step_limit=3)
