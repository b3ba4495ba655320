"""The resource limits a policy can reach, named alike whichever platform stopped it.

Three platforms hold a policy to its limits: the sandbox (evaluator/sandbox.py) samples what a
local policy uses and stops it; a container engine (worker/containers.py) kills a container at
its memory limit and refuses it processes past its pids limit; Kubernetes kills a container at its
memory limit (`OOMKilled`). Each ends the evaluation with the same failure kind and a reason of
the same shape, "<who> stopped it at its memory limit of 1024 MiB", so a participant reads the
same words whichever executor ran the submission (docs/metrics.md, "Failures").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from evaluator.results import EvaluationResult

LimitKind = Literal["memory_limit", "process_limit", "file_size_limit"]

SANDBOX = "the sandbox stopped it"
ENGINE = "the container engine stopped it"
KUBERNETES = "Kubernetes stopped it"


@dataclass(frozen=True)
class Breach:
    """A limit the policy reached, in the words its result gives."""

    kind: LimitKind
    detail: str


def memory_breach(by: str, memory_mib: int) -> Breach:
    return Breach("memory_limit", f"{by} at its memory limit of {memory_mib} MiB")


def process_breach(by: str, processes: int) -> Breach:
    return Breach("process_limit", f"{by} at its limit of {processes} processes")


def scratch_breach(by: str, directory: str, scratch_mib: int) -> Breach:
    return Breach("file_size_limit", f"{by} with its {directory} full ({scratch_mib} MiB)")


def with_detail(reason: str, detail: str) -> str:
    """An abort's reason with what the platform saw of the policy's end."""
    return f"{reason} ({detail})"


def charged(result: EvaluationResult, breach: Breach) -> EvaluationResult:
    """An aborted `result` charged to `breach`: its abort, and the episode it broke in, take
    the limit's kind and a reason that names it, as the evaluator itself gives them where it
    sees the limit (evaluator/runner.py). For a platform that learns of the limit only after
    the result was written: Kubernetes, from the policy container's status."""
    abort = result.abort
    if result.status != "aborted" or abort is None or abort.kind == breach.kind:
        return result
    reason = (
        abort.reason if breach.detail in abort.reason else with_detail(abort.reason, breach.detail)
    )
    conditions = []
    for condition in result.conditions:
        tasks = []
        for task in condition.tasks:
            episodes = [
                e.model_copy(update={"failure": breach.kind, "failure_reason": reason})
                if e.failure == abort.kind
                else e
                for e in task.episodes
            ]
            tasks.append(task.model_copy(update={"episodes": episodes}))
        conditions.append(condition.model_copy(update={"tasks": tasks}))
    return result.model_copy(
        update={
            "abort": abort.model_copy(update={"kind": breach.kind, "reason": reason}),
            "conditions": conditions,
        }
    )
