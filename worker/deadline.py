"""How long an attempt may take on the wall clock, whichever executor runs it (pure).

The policy's budget counts only the time it takes to answer; the evaluator's own work
(simulating, rebuilding scenes, rendering the recorded episodes' frames) comes on top. The
docker executor reports this limit to the server as the attempt's deadline; a Kubernetes Job's
`activeDeadlineSeconds` is the same limit plus the time to schedule its pods and pull their
images (`worker.kubernetes.manifest.active_deadline_for`), since the Job's clock starts first.
"""

from __future__ import annotations

from evaluator.plan import EvaluationPlan

RUN_ESTIMATE_GRACE_S = 120.0
"""Beyond the run's estimated wall time (`wall_clock_limit_s`), before the reconciler times
the attempt out. Not a Kubernetes Job's grace, which follows a deadline Kubernetes enforces."""
SIM_STEPS_PER_S = 20.0  # a slow machine's pace, for the evaluator's own share of the time
SCENE_BUILD_S = 2.0  # each episode rebuilds its scene (evaluator/sim.py)
FRAME_RENDER_S = 0.25  # a slow machine's time to render a video frame (45-100 ms on lavapipe)


def wall_clock_limit_s(plan: EvaluationPlan) -> float:
    """How long the whole attempt may take before the reconciler times it out: the policy's
    budget (which counts only its own answers) plus the evaluator's own time, generously,
    rendering the recorded episodes' frames included."""
    own = sum(
        len(run.seeds) * (run.max_episode_steps / SIM_STEPS_PER_S + SCENE_BUILD_S)
        + sum(plan.records(run, i) for i in range(len(run.seeds)))
        * (run.max_episode_steps + 1)
        * FRAME_RENDER_S
        for run in plan.runs
    )
    return plan.limits.budget_s * 1.1 + own + RUN_ESTIMATE_GRACE_S
