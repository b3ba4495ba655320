"""What a challenge's policy receives and must return, generated from its suite: the
getting-started page shows it, so it can never drift from what the evaluator does."""

from __future__ import annotations

from dataclasses import dataclass

from evaluator.suite import Condition, Suite

EVERY_ENTRY = "every entry of the observation mode"
# What each condition does to what the policy sees, in words (docs/protocol.md, §6).
CONDITION_EFFECTS = {
    "nominal": "observations and actions as the task gives them",
    "obs_noise": "Gaussian noise (sigma {sigma}) on every float observation",
    "action_delay": "the observation is {steps} steps old",
    "low_freq": "{control_freq} Hz control, the same simulated time per episode",
    "obs_mode": "the same scenes seen through the {obs_mode} observation mode",
}


@dataclass(frozen=True)
class TaskContract:
    env_id: str
    obs_mode: str
    control_mode: str
    max_episode_steps: int
    episodes: int
    instruction: str


@dataclass(frozen=True)
class Contract:
    """The observation and action contract of one suite."""

    tasks: list[TaskContract]
    observation_keys: list[str]
    chunk_length: int
    chunk_executed: int
    conditions: list[tuple[str, str]]  # (name, what it changes)
    connect_timeout_s: float
    first_call_timeout_s: float
    call_timeout_s: float
    budget_s: float
    gpus: int
    public_phases: list[str]


def contract_of(suite: Suite) -> Contract:
    """The contract a policy meets in `suite`'s evaluations."""
    return Contract(
        tasks=[
            TaskContract(
                env_id=t.env_id,
                obs_mode=t.obs_mode,
                control_mode=t.control_mode,
                max_episode_steps=t.max_episode_steps,
                episodes=t.episodes,
                instruction=t.instruction,
            )
            for t in suite.tasks
        ],
        observation_keys=list(suite.observation_keys or [EVERY_ENTRY]),
        chunk_length=suite.action_chunks.max_length,
        chunk_executed=suite.action_chunks.executed,
        conditions=[(c.name, condition_effect(c)) for c in suite.conditions],
        connect_timeout_s=suite.limits.connect_timeout_s,
        first_call_timeout_s=suite.limits.first_call_timeout_s,
        call_timeout_s=suite.limits.call_timeout_s,
        budget_s=suite.limits.budget_s,
        gpus=suite.policy.gpus,
        public_phases=[name for name, p in suite.phases.items() if p.seeds.kind == "public"],
    )


def condition_effect(condition: Condition) -> str:
    """What a condition changes for the policy, in words."""
    params = condition.params.model_dump()
    return CONDITION_EFFECTS[params["kind"]].format(**params)
