"""Running verification (docs/verification.md): the organizer's reference solution on 1 and 2
workers and the bundled random policy, on the dev seeds, into a report
(`evaluator/verification.py`) with each task's success, step headroom and evaluation cost."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from evaluator.bundled import LOCAL_PREFIX, bundled_policies
from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EvaluationResult, TaskResult, episode_records
from evaluator.sources import LocalDirectory
from evaluator.suite import Suite, VerificationThresholds
from evaluator.verification import (
    TaskVerification,
    VerificationReport,
    failures,
    verification_phase,
)

RANDOM_POLICY = "random"
WORKERS = (1, 2)  # the reference runs with each; their records must be equal


def verification_plan(suite: Suite, *, episodes: int | None) -> EvaluationPlan:
    """Every task under the suite's first condition, on the dev seeds, nothing filmed."""
    return build_plan(
        suite,
        verification_phase(suite),
        conditions=[suite.conditions[0].name],
        episodes=episodes,
        videos=0,
    )


def policy_label(directory: Path) -> str:
    """How the report names a policy: `local:NAME` for a bundled one (the same on every
    machine), else its directory."""
    bundled = {path.resolve(): name for name, path in bundled_policies().items()}
    name = bundled.get(directory.resolve())
    return f"{LOCAL_PREFIX}{name}" if name else f"dir:{directory.resolve()}"


def reference_policy(reference: str) -> Path:
    """The reference's policy directory: `reference` itself, or the bundled policy of that
    name; ValueError naming both where neither holds a `policy.py`."""
    policy = Path(reference)
    if not policy.is_dir():
        policy = bundled_policies().get(reference, policy)
    if not (policy / "policy.py").is_file():
        known = ", ".join(bundled_policies())
        raise ValueError(
            f"--reference {reference}: no policy.py there, and no bundled policy of that name "
            f"(bundled: {known})"
        )
    return policy


def random_policy() -> Path:
    """The bundled random policy's directory."""
    return bundled_policies()[RANDOM_POLICY]


def verify(
    suite: Suite,
    reference: Path,
    *,
    episodes: int | None = None,
    on_run: Callable[[str, EvaluationPlan], None] = lambda _name, _plan: None,
    now: Callable[[], datetime] = lambda: datetime.now(UTC),
) -> VerificationReport:
    """Run the reference on 1 worker, the random policy, the reference on 2 workers, on the
    dev seeds, and judge them against the suite's thresholds. `suite` is as loaded (its
    packages pinned); `reference` is a policy directory; `on_run` hears of each run as it
    starts."""
    plan = verification_plan(suite, episodes=episodes)
    reference_source = LocalDirectory(reference)
    chance_source = LocalDirectory(random_policy())
    runs: list[tuple[str, EvaluationResult]] = []
    for name, source, workers in (
        ("reference, 1 worker", reference_source, WORKERS[0]),
        ("random policy", chance_source, 1),
        ("reference, 2 workers", reference_source, WORKERS[1]),
    ):
        on_run(name, plan)
        runs.append((name, evaluate(plan, source, workers=workers)))
    (_, one), (_, chance), (_, two) = runs
    report = VerificationReport(
        suite=plan.suite,
        phase=plan.phase,
        condition=plan.runs[0].condition.name,
        reference=policy_label(reference),
        random=policy_label(random_policy()),
        versions=one.versions,
        created_at=now(),
        thresholds=suite.verification,
        aborted=[f"{name}: {r.abort.reason}" for name, r in runs if r.abort is not None],
        tasks=[
            measured(
                suite.thresholds(run.env_id),
                run.max_episode_steps,
                task,
                chance_task,
                differing(one, two, run.env_id),
            )
            for run, task, chance_task in zip(
                plan.runs, one.conditions[0].tasks, chance.conditions[0].tasks, strict=True
            )
        ],
        failures=[],
    )
    report.failures = failures(report, suite)
    return report


def measured(
    thresholds: VerificationThresholds,
    max_episode_steps: int,
    reference: TaskResult,
    chance: TaskResult,
    differing: list[int],
) -> TaskVerification:
    """One task's line of the report, from the reference's and the random policy's results."""
    solved = [e.steps for e in reference.episodes if e.success_once]
    return TaskVerification(
        env_id=reference.env_id,
        episodes=reference.episodes_planned,
        max_episode_steps=max_episode_steps,
        reference_successes=reference.successes,
        random_successes=chance.successes,
        reference_steps_max=max(solved) if solved else None,
        seconds_per_episode=sum(e.wall_time_s for e in reference.episodes)
        / max(len(reference.episodes), 1),
        differing_episodes=differing,
        thresholds=thresholds,
    )


def differing(one: EvaluationResult, two: EvaluationResult, env_id: str) -> list[int]:
    """The indexes of a task's episodes whose records differ between two results."""
    first, second = ([r for r in episode_records(r) if r["task"] == env_id] for r in (one, two))
    if len(first) != len(second):
        return list(range(max(len(first), len(second))))
    return [i for i, (a, b) in enumerate(zip(first, second, strict=True)) if a != b]
