"""Whether the evaluation namespace's ResourceQuotas have room for one more Job (pure).

A worker starts a Job only when every quota has headroom for all of it: its pods, their
requests and limits, the Job itself and its Secret. Without this check, workers that outnumber
the quota (a rolling restart's draining and new workers side by side, a scale-down of the
quota) would create Jobs whose pods the quota then refuses, and those attempts would end as
the cluster's errors. The quota itself stays the authority: the API server refuses what does
not fit, and the worker treats such a refusal as "no room yet" too.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from kubernetes.utils import parse_quantity as _parse

_COMPUTE = ("cpu", "memory", "ephemeral-storage")


@dataclass(frozen=True)
class Quota:
    """One ResourceQuota as the API server reports it: its limits and what is used."""

    name: str
    hard: Mapping[str, str]
    used: Mapping[str, str]


def quota_of(obj: Any) -> Quota:
    """A ResourceQuota object from the client (V1ResourceQuota) or a dict."""
    if isinstance(obj, Mapping):
        meta, status = obj.get("metadata") or {}, obj.get("status") or {}
        return Quota(meta.get("name", "?"), status.get("hard") or {}, status.get("used") or {})
    status = obj.status
    hard = (status.hard if status is not None else None) or {}
    used = (status.used if status is not None else None) or {}
    return Quota(obj.metadata.name if obj.metadata is not None else "?", hard, used)


def demand(
    job: Mapping[str, Any], *, overhead: Mapping[str, str] | None = None
) -> dict[str, Decimal]:
    """What one Job takes from a quota, by resource name as quotas spell them. A pod with a
    RuntimeClass is given that class's `overhead` (its `podFixed`) at admission, and the quota
    counts it in the pod's requests and limits (`PodUsageFunc` in
    pkg/quota/v1/evaluator/core/pods.go, through `PodRequests`/`PodLimits`)."""
    spec = job["spec"]
    pods = int(spec.get("parallelism") or 1)
    pod_spec = spec["template"]["spec"]
    containers = [*pod_spec.get("initContainers", []), *pod_spec.get("containers", [])]
    if overhead and pod_spec.get("runtimeClassName"):
        costs = {"requests": dict(overhead), "limits": dict(overhead)}
        containers.append({"name": "(RuntimeClass overhead)", "resources": costs})
    needs: dict[str, Decimal] = {
        "pods": Decimal(pods),
        "count/pods": Decimal(pods),
        "count/jobs.batch": Decimal(1),
        "secrets": Decimal(1),
        "count/secrets": Decimal(1),
    }
    for kind in ("requests", "limits"):
        for name, value in _summed(containers, kind).items():
            needs[f"{kind}.{name}"] = value * pods
            if kind == "requests" and name in _COMPUTE:
                needs[name] = value * pods  # `cpu` in a quota means requests.cpu
    return needs


def shortfall(quotas: Iterable[Quota], needs: Mapping[str, Decimal]) -> str | None:
    """Why the Job does not fit now (the first quota short of room), or None when it fits."""
    for quota in quotas:
        for resource, hard in sorted(quota.hard.items()):
            if resource not in needs:
                continue  # a resource this Job does not use
            limit = parse_quantity(hard)
            used = parse_quantity(quota.used.get(resource, "0"))
            if used + needs[resource] > limit:
                return (
                    f"quota {quota.name}: {resource} {_show(used)} used of {_show(limit)}, "
                    f"the Job needs {_show(needs[resource])}"
                )
    return None


def never_fits(quotas: Iterable[Quota], needs: Mapping[str, Decimal]) -> str | None:
    """Why the Job could not fit even in an empty namespace, or None."""
    for quota in quotas:
        for resource, hard in sorted(quota.hard.items()):
            if resource in needs and needs[resource] > parse_quantity(hard):
                return (
                    f"quota {quota.name} allows {resource}={_show(parse_quantity(hard))}, "
                    f"less than one evaluation Job needs ({_show(needs[resource])})"
                )
    return None


def parse_quantity(value: str) -> Decimal:
    """A Kubernetes quantity ("500m", "2Gi") as a number."""
    parsed: Decimal = _parse(value)  # type: ignore[no-untyped-call]
    return parsed


def _summed(containers: Iterable[Mapping[str, Any]], kind: str) -> dict[str, Decimal]:
    total: dict[str, Decimal] = {}
    for container in containers:
        for name, value in ((container.get("resources") or {}).get(kind) or {}).items():
            total[name] = total.get(name, Decimal(0)) + parse_quantity(value)
    return total


def _show(value: Decimal) -> str:
    return f"{value.normalize():f}"
