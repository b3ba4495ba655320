"""A concrete evaluation plan: what the evaluator runs, with seeds already resolved."""

from __future__ import annotations

from collections.abc import Sequence

from pydantic import BaseModel, ConfigDict, Field

from evaluator.results import SuiteRef
from evaluator.suite import (
    NO_CHUNKS,
    ActionChunks,
    Condition,
    Limits,
    ObsMode,
    PolicyResources,
    Suite,
    SuiteError,
    TaskConfig,
    phase_seeds,
)


class TaskRun(BaseModel):
    """One task under one condition, on concrete seeds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    env_id: str
    obs_mode: str
    control_mode: str
    sim_backend: str
    max_episode_steps: int = Field(ge=1)
    condition: Condition
    seeds: tuple[int, ...]
    instruction: str = ""
    observation_keys: tuple[str, ...] | None = None
    """The observation entries the policy may see (None: all)."""


def task_run(suite: Suite, task: TaskConfig, condition: Condition, seeds: Sequence[int]) -> TaskRun:
    """A suite's task under one of its conditions, on these seeds (an `obs_mode` condition
    shows the task through another observation mode)."""
    params = condition.params
    return TaskRun(
        env_id=task.env_id,
        obs_mode=params.obs_mode if isinstance(params, ObsMode) else task.obs_mode,
        control_mode=task.control_mode,
        sim_backend=task.sim_backend,
        max_episode_steps=task.max_episode_steps,
        condition=condition,
        seeds=tuple(seeds),
        instruction=task.instruction,
        observation_keys=suite.observation_keys,
    )


class EvaluationPlan(BaseModel):
    """Everything the evaluator needs; it never sees a suite's seed secret."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    suite: SuiteRef
    phase: str
    limits: Limits
    runs: tuple[TaskRun, ...]
    ignore_terminations: bool = False
    action_chunks: ActionChunks = NO_CHUNKS
    videos: int = Field(default=0, ge=0)
    """Episodes recorded per task run: those with an index below it (the first N)."""
    video_conditions: tuple[str, ...] | None = None
    """The conditions whose task runs are recorded (None: every one)."""
    video_size: int | None = None
    """Frames' side in pixels (None: the task's render camera's own size)."""
    video_fps: int | None = None
    """At most this many frames per second of control time (None: a frame after every step)."""
    policy: PolicyResources = PolicyResources()
    """What the policy's container is given (the suite's `policy`: GPUs)."""
    packages: dict[str, str | None] = {}
    """The suite's task packages, in import order, each with the version the suite was loaded
    with (None: not pinned): the evaluator imports them, and refuses another version."""

    def records(self, run: TaskRun, index: int) -> bool:
        """Whether episode `index` of task run `run` is recorded as a video."""
        wanted = self.video_conditions is None or run.condition.name in self.video_conditions
        return wanted and index < self.videos

    def frame_stride(self, control_freq: int) -> int:
        """Film every this many steps: the fewest that keep the video within `video_fps`."""
        if self.video_fps is None:
            return 1
        return max(1, -(-control_freq // self.video_fps))

    def episode_count(self) -> int:
        """Episodes in the whole plan."""
        return sum(len(run.seeds) for run in self.runs)


def build_plan(
    suite: Suite,
    phase: str,
    *,
    tasks: Sequence[str] | None = None,
    conditions: Sequence[str] | None = None,
    episodes: int | None = None,
    secret: bytes | None = None,
    record_video: bool = False,
    videos: int | None = None,
) -> EvaluationPlan:
    """Resolve a suite, a phase and optional narrowing into concrete task runs.

    `videos` episodes of each task run are recorded (None: the suite's `videos`);
    `record_video` asks for at least the first one, whatever the suite says.
    """
    if episodes is not None and episodes < 1:
        raise SuiteError("episodes must be at least 1")
    if videos is not None and videos < 0:
        raise SuiteError("videos must not be negative")
    recorded = suite.videos if videos is None else videos
    selected_tasks = [suite.task(t) for t in tasks] if tasks else list(suite.tasks)
    selected_conditions = (
        [suite.condition(c) for c in conditions] if conditions else list(suite.conditions)
    )
    suite.phase(phase)
    runs = [
        task_run(
            suite,
            task,
            condition,
            phase_seeds(
                suite,
                phase,
                task.env_id,
                episodes if episodes is not None else task.episodes,
                secret=secret,
            ),
        )
        for condition in selected_conditions
        for task in selected_tasks
    ]
    return suite_plan(
        suite,
        phase,
        runs,
        videos=max(recorded, 1) if record_video else recorded,
        # Asked for on the command line: every condition, whatever the suite limits it to.
        video_conditions=None if record_video else suite.video_conditions,
    )


def suite_plan(
    suite: Suite,
    phase: str,
    runs: Sequence[TaskRun],
    *,
    videos: int,
    video_conditions: tuple[str, ...] | None,
) -> EvaluationPlan:
    """The plan of these task runs of `suite`, with the suite's limits and settings."""
    return EvaluationPlan(
        suite=SuiteRef(name=suite.name, version=suite.version, sha256=suite.sha256()),
        phase=phase,
        limits=suite.limits,
        runs=tuple(runs),
        ignore_terminations=suite.ignore_terminations,
        action_chunks=suite.action_chunks,
        videos=videos,
        video_conditions=video_conditions,
        video_size=suite.video_size,
        video_fps=suite.video_fps,
        policy=suite.policy,
        packages={name: suite.package_versions.get(name) for name in suite.packages},
    )
