"""The Job controller's podFailurePolicy, as the API-server double applies it to a failed pod.

`matchPodFailurePolicy` in pkg/controller/job/pod_failure_policy.go: the rules in order, the
first that matches decides; `onExitCodes` looks at terminated containers with a non-zero exit
code (`getMatchingContainerFromList`), `onPodConditions` at the pod's conditions by type and
status (`matchOnPodConditions`). A FailJob rule fails the Job with reason PodFailurePolicy and
a message naming the pod and the rule; Ignore does not count the pod (the controller makes a
new one); Count, or no rule at all, counts it against `backoffLimit`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

Json = dict[str, Any]
Action = Literal["FailJob", "Ignore", "Count"]
POD_FAILURE_POLICY = "PodFailurePolicy"
"""The Job's failure reason when a FailJob rule matched (`batch.JobReasonPodFailurePolicy`)."""


@dataclass(frozen=True)
class Match:
    """What the policy decides for one failed pod: its action, and the Job's failure message
    when the action is FailJob."""

    action: Action
    message: str = ""


def match_pod_failure_policy(job: Json, pod: Json) -> Match:
    """The first rule of the Job's podFailurePolicy that `pod` (failed) matches; Count when
    none does, as when the Job has no policy."""
    rules = ((job.get("spec") or {}).get("podFailurePolicy") or {}).get("rules") or []
    meta, status = pod["metadata"], pod.get("status") or {}
    who = f"{meta['namespace']}/{meta['name']}"
    for index, rule in enumerate(rules):
        action: Action = rule["action"]
        if "onExitCodes" in rule:
            container = _exit_code_match(status, rule["onExitCodes"])
            if container is not None:
                code = container["state"]["terminated"]["exitCode"]
                what = f"Container {container['name']} for pod {who} failed with exit code {code}"
                return Match(action, f"{what} matching {action} rule at index {index}")
        elif "onPodConditions" in rule:
            condition = _condition_match(status, rule["onPodConditions"])
            if condition is not None:
                what = f"Pod {who} has condition {condition}"
                return Match(action, f"{what} matching {action} rule at index {index}")
    return Match("Count")


def _exit_code_match(status: Json, requirement: Json) -> Json | None:
    containers = [*status.get("containerStatuses", []), *status.get("initContainerStatuses", [])]
    for container in containers:
        terminated = (container.get("state") or {}).get("terminated")
        if terminated is None or not terminated.get("exitCode"):
            continue  # still terminating, or exited 0: no exit code to match
        if requirement.get("containerName") not in (None, container["name"]):
            continue
        listed = terminated["exitCode"] in requirement["values"]
        if listed == (requirement["operator"] == "In"):
            return container
    return None


def _condition_match(status: Json, patterns: list[Json]) -> str | None:
    for condition in status.get("conditions") or []:
        for pattern in patterns:
            if (condition["type"], condition["status"]) == (pattern["type"], pattern["status"]):
                return str(condition["type"])
    return None
