"""Fixtures for evaluator tests: small suites and policies written on the fly."""

from __future__ import annotations

import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EvaluationResult
from evaluator.sources import LocalDirectory
from evaluator.suite import Suite, load_suite

HERE = Path(__file__).parent
REPO = HERE.parents[1]
SCRIPTED = REPO / "examples" / "policies" / "scripted"
RANDOM = REPO / "examples" / "policies" / "random"

# A deterministic policy whose actions depend on the observation, so any difference in what the
# policy sees shows up in the episode records.
REACTIVE_POLICY = """
import numpy as np
from manieval_sdk import Policy, serve

def flat(obs):
    if isinstance(obs, dict):
        return np.concatenate([flat(obs[k]) for k in sorted(obs)])
    return np.asarray(obs, dtype=np.float64).reshape(-1)

class Reactive(Policy):
    def act(self, obs):
        x = flat(obs)
        n = self.spec.action_shape[0]
        weights = np.cos(np.arange(n * x.size).reshape(n, x.size))
        return np.tanh(weights @ x).astype(np.float32)

if __name__ == "__main__":
    serve(Reactive())
"""


def tiny_suite() -> Suite:
    return load_suite(HERE / "tiny_suite.yaml")


def tiny_plan(**kwargs: object) -> EvaluationPlan:
    return build_plan(tiny_suite(), "dev", **kwargs)  # type: ignore[arg-type]


def with_limits(plan: EvaluationPlan, **limits: float) -> EvaluationPlan:
    return plan.model_copy(update={"limits": plan.limits.model_copy(update=limits)})


def run(plan: EvaluationPlan, policy: Path, *, workers: int = 1) -> EvaluationResult:
    return evaluate(plan, LocalDirectory(policy), workers=workers)


@pytest.fixture
def make_policy(tmp_path: Path) -> Callable[[str], Path]:
    """Write `policy.py` with the given source into a fresh directory."""
    counter = iter(range(1000))

    def write(source: str) -> Path:
        directory = tmp_path / f"policy{next(counter)}"
        directory.mkdir()
        (directory / "policy.py").write_text(textwrap.dedent(source))
        return directory

    return write
