"""What a Job takes from the namespace's ResourceQuotas, and whether it fits (pure)."""

from __future__ import annotations

from decimal import Decimal

import pytest

from tests.worker.k8s_specs import (
    make_spec,
)
from worker.kubernetes.manifest import build_job
from worker.kubernetes.quota import Quota, demand, never_fits, quota_of, shortfall


def test_a_job_demands_its_pods_their_requests_and_limits_and_itself() -> None:
    needs = demand(build_job(make_spec(shards=3)))
    assert needs["pods"] == needs["count/pods"] == Decimal(3)
    assert needs["count/jobs.batch"] == needs["secrets"] == Decimal(1)
    job = build_job(make_spec(shards=3))
    pod = job["spec"]["template"]["spec"]
    containers = [*pod["initContainers"], *pod["containers"]]
    cpu = sum(Decimal(str(_cores(c["resources"]["requests"]["cpu"]))) for c in containers)
    assert needs["requests.cpu"] == needs["cpu"] == cpu * 3
    assert needs["limits.memory"] > 0


def test_a_pod_with_a_runtime_class_demands_its_overhead_too() -> None:
    """The quota counts the RuntimeClass's overhead in each pod's requests and limits."""
    gvisor = build_job(make_spec(shards=2, runtime_class_name="gvisor"))
    overhead = {"cpu": "100m", "memory": "128Mi"}
    bare, sandboxed = demand(gvisor), demand(gvisor, overhead=overhead)
    for resource in ("requests.cpu", "limits.cpu", "cpu"):
        assert sandboxed[resource] - bare[resource] == Decimal("0.2")  # 100m a pod
    for resource in ("requests.memory", "limits.memory", "memory"):
        assert sandboxed[resource] - bare[resource] == 2 * 128 * 2**20
    # Without a RuntimeClass no overhead is admitted with the pod, whatever is configured.
    assert demand(build_job(make_spec()), overhead=overhead) == demand(build_job(make_spec()))


def _cores(value: str) -> float:
    return int(value[:-1]) / 1000 if value.endswith("m") else float(value)


@pytest.mark.parametrize(
    ("hard", "used", "expected"),
    [
        ({"pods": "4"}, {"pods": "2"}, None),
        ({"pods": "4"}, {"pods": "3"}, "quota q: pods 3 used of 4, the Job needs 2"),
        ({"requests.cpu": "10"}, {"requests.cpu": "9500m"}, "quota q: requests.cpu 9.5 used"),
        ({"limits.memory": "64Gi"}, {}, None),
        ({"services": "1"}, {"services": "1"}, None),  # a resource the Job does not use
    ],
)
def test_shortfall_names_the_first_quota_without_room(
    hard: dict[str, str], used: dict[str, str], expected: str | None
) -> None:
    needs = demand(build_job(make_spec(shards=2)))
    found = shortfall([Quota("q", hard, used)], needs)
    if expected is None:
        assert found is None
    else:
        assert found is not None
        assert found.startswith(expected)


def test_a_quota_smaller_than_one_job_is_told_apart_from_a_full_one() -> None:
    needs = demand(build_job(make_spec(shards=3)))
    assert never_fits([Quota("q", {"pods": "3"}, {"pods": "3"})], needs) is None
    assert never_fits([Quota("q", {"pods": "2"}, {})], needs) == (
        "quota q allows pods=2, less than one evaluation Job needs (3)"
    )


def test_quotas_read_from_the_api_as_dicts_or_client_models() -> None:
    from kubernetes.client import V1ObjectMeta, V1ResourceQuota, V1ResourceQuotaStatus

    model = V1ResourceQuota(
        metadata=V1ObjectMeta(name="eval"),
        status=V1ResourceQuotaStatus(hard={"pods": "2"}, used={"pods": "1"}),
    )
    raw = {"metadata": {"name": "eval"}, "status": {"hard": {"pods": "2"}, "used": {"pods": "1"}}}
    assert quota_of(model) == quota_of(raw) == Quota("eval", {"pods": "2"}, {"pods": "1"})
    assert quota_of({"metadata": {"name": "new"}}) == Quota("new", {}, {})  # not yet counted
