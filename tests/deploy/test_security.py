"""k8s/: the isolation ManiEval's threat model rests on (docs/security.md), on every overlay.

Pods meet Pod Security "restricted" field by field, only the worker holds a token and its Role
is no wider than running evaluation Jobs, and evaluation pods have no network at all.
"""

from __future__ import annotations

import copy
from typing import Any

import pytest

from tests.deploy.manifests import (
    CONTROL_PLANE,
    EVALUATIONS,
    OVERLAYS,
    Json,
    containers,
    find,
    one,
    pod_templates,
    quantity,
    render,
    selects,
)
from tests.worker.test_k8s_manifest import restricted_violations
from worker.kubernetes.manifest import build_network_policy, job_labels

WORKER_SA = {"kind": "ServiceAccount", "name": "manieval-worker", "namespace": CONTROL_PLANE}
WORKER_MAY = {
    ("batch", "jobs"): {"create", "get", "list", "watch", "delete"},
    ("", "pods"): {"get", "list", "watch", "delete"},
    ("", "pods/log"): {"get"},
}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_container_requests_and_limits_cpu_and_memory(overlay: str):
    for workload, template in pod_templates(render(overlay)):
        for c in containers(template["spec"]):
            where = f"{workload['metadata']['name']}/{c['name']}"
            resources = c.get("resources", {})
            for resource in ("cpu", "memory"):
                request = resources.get("requests", {}).get(resource)
                limit = resources.get("limits", {}).get(resource)
                assert request is not None, f"{where}: no {resource} request"
                assert limit is not None, f"{where}: no {resource} limit"
                assert quantity(request) <= quantity(limit), f"{where}: {resource}"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_pod_meets_the_restricted_profile(overlay: str):
    for workload, template in pod_templates(render(overlay)):
        assert restricted_violations(template["spec"]) == [], workload["metadata"]["name"]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_both_namespaces_enforce_audit_and_warn_the_restricted_profile(overlay: str):
    namespaces = {n["metadata"]["name"]: n for n in find(render(overlay), "Namespace")}
    assert set(namespaces) == {CONTROL_PLANE, EVALUATIONS}
    for namespace in namespaces.values():
        labels = namespace["metadata"]["labels"]
        for mode in ("enforce", "audit", "warn"):
            assert labels[f"pod-security.kubernetes.io/{mode}"] == "restricted"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_pods_get_a_scratch_tmp_and_no_service_links(overlay: str):
    # Service links would inject variables named after Services, e.g. MANIEVAL_API_PORT, into
    # the environment the settings (MANIEVAL_*) are read from.
    for workload, template in pod_templates(render(overlay)):
        spec = template["spec"]
        assert spec.get("enableServiceLinks") is False, workload["metadata"]["name"]
        scratch = {v["name"] for v in spec.get("volumes", []) if "emptyDir" in v}
        for c in containers(spec):  # the root filesystem is read-only: /tmp is the scratch
            tmp = [m["name"] for m in c.get("volumeMounts", []) if m["mountPath"] == "/tmp"]
            assert tmp, f"{c['name']}: nothing mounted on /tmp"
            assert tmp[0] in scratch, f"{c['name']}: /tmp is not an emptyDir"


def _token_mounted(objects: list[Json], spec: Json, namespace: str) -> bool:
    if "automountServiceAccountToken" in spec:
        return bool(spec["automountServiceAccountToken"])
    account = find(objects, "ServiceAccount", spec.get("serviceAccountName", "default"))
    mine = [a for a in account if a["metadata"]["namespace"] == namespace]
    return bool(mine[0].get("automountServiceAccountToken", True)) if mine else True


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_only_the_worker_holds_a_service_account_token(overlay: str):
    objects = render(overlay)
    holders = {
        workload["metadata"]["name"]
        for workload, template in pod_templates(objects)
        if _token_mounted(objects, template["spec"], workload["metadata"]["namespace"])
    }
    assert holders == {"manieval-worker"}
    for account in find(objects, "ServiceAccount"):
        assert account.get("automountServiceAccountToken") is False, account["metadata"]["name"]
    worker = one(objects, "Deployment", "manieval-worker")["spec"]["template"]["spec"]
    assert worker["serviceAccountName"] == WORKER_SA["name"]


def rbac_problems(objects: list[Json]) -> list[str]:
    """Every way the RBAC objects grant more than running evaluation Jobs."""
    problems = [f"{o['kind']} {o['metadata']['name']}" for o in objects if "Cluster" in o["kind"]]
    roles = find(objects, "Role")
    if [(r["metadata"]["name"], r["metadata"]["namespace"]) for r in roles] != [
        ("manieval-worker", EVALUATIONS)
    ]:
        problems.append(f"roles: {[r['metadata'] for r in roles]}")
    for role in roles:
        for rule in role["rules"]:
            if set(rule) - {"apiGroups", "resources", "verbs"}:
                problems.append(f"rule with {sorted(set(rule))}")
            for group in rule.get("apiGroups", []):
                for resource in rule.get("resources", []):
                    allowed = WORKER_MAY.get((group, resource), set())
                    extra = set(rule["verbs"]) - allowed
                    if extra:
                        problems.append(f"{group}/{resource}: {sorted(extra)}")
    for binding in find(objects, "RoleBinding"):
        if (
            binding["metadata"]["namespace"] != EVALUATIONS
            or binding["roleRef"]
            != {
                "apiGroup": "rbac.authorization.k8s.io",
                "kind": "Role",
                "name": "manieval-worker",
            }
            or binding["subjects"] != [WORKER_SA]
        ):
            problems.append(f"binding {binding['metadata']['name']}")
    return problems


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_worker_may_only_run_jobs_and_read_their_pods_in_the_evaluation_namespace(
    overlay: str,
):
    objects = render(overlay)
    assert rbac_problems(objects) == []
    assert len(find(objects, "RoleBinding")) == 1


WIDER: dict[str, Any] = {
    "a wildcard verb": lambda role: role["rules"][0].update(verbs=["*"]),
    "a wildcard resource": lambda role: role["rules"][1].update(resources=["*"]),
    "secrets": lambda role: role["rules"].append(
        {"apiGroups": [""], "resources": ["secrets"], "verbs": ["get"]}
    ),
    "pods/exec": lambda role: role["rules"][2].update(resources=["pods/log", "pods/exec"]),
    "patching jobs": lambda role: role["rules"][0]["verbs"].append("patch"),
    "another namespace": lambda role: role["metadata"].update(namespace="default"),
}


@pytest.mark.parametrize("change", sorted(WIDER))
def test_the_rbac_check_catches_a_wider_role(change: str):
    objects = copy.deepcopy(render("production"))
    WIDER[change](one(objects, "Role", "manieval-worker"))
    assert rbac_problems(objects) != []


def test_the_rbac_check_catches_a_cluster_role():
    objects = copy.deepcopy(render("production"))
    role = copy.deepcopy(one(objects, "Role", "manieval-worker"))
    role["kind"] = "ClusterRole"
    assert rbac_problems([*objects, role]) != []


def rules(objects: list[Json], namespace: str, labels: dict[str, str], kind: str) -> list[Json]:
    """The rules of `kind` (Ingress or Egress) that apply to a pod with `labels`; an empty list
    when some policy isolates the pod in that direction and none allows anything."""
    selecting = [
        p
        for p in find(objects, "NetworkPolicy")
        if p["metadata"]["namespace"] == namespace
        and kind in p["spec"]["policyTypes"]
        and selects(p["spec"]["podSelector"], labels)
    ]
    assert selecting, f"no policy isolates {labels} for {kind}: everything is allowed"
    key = kind.lower()
    return [rule for p in selecting for rule in p["spec"].get(key, [])]


def _ports(rule_list: list[Json]) -> set[int]:
    return {port["port"] for rule in rule_list for port in rule.get("ports", [])}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_evaluation_pods_have_no_network_at_all(overlay: str):
    objects = render(overlay)
    labels = {**job_labels(41, 2), "batch.kubernetes.io/job-completion-index": "0"}
    assert rules(objects, EVALUATIONS, labels, "Egress") == []
    assert rules(objects, EVALUATIONS, labels, "Ingress") == []
    assert rules(objects, EVALUATIONS, {"anything": "else"}, "Egress") == []


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_isolation_policy_is_the_one_the_worker_builds(overlay: str):
    policy = one(render(overlay), "NetworkPolicy", "manieval-evaluations-isolated")
    assert policy == build_network_policy(EVALUATIONS)


def component(name: str) -> dict[str, str]:
    return {"app.kubernetes.io/name": "manieval", "app.kubernetes.io/component": name}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_control_plane_admits_only_the_ingress_controller_to_the_api(overlay: str):
    objects = render(overlay)
    (api_in,) = rules(objects, CONTROL_PLANE, component("api"), "Ingress")
    assert api_in["from"] == [
        {"namespaceSelector": {"matchLabels": {"kubernetes.io/metadata.name": "ingress-nginx"}}}
    ]
    assert _ports([api_in]) == {8000}
    for name in ("worker", "beat", "migrate"):
        assert rules(objects, CONTROL_PLANE, component(name), "Ingress") == [], name


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_control_plane_pods_reach_only_what_they_need(overlay: str):
    objects = render(overlay)
    dns = {53}
    expected = {
        "api": dns | {5432, 6379, 443},  # registries: pinning tags to digests
        "worker": dns | {5432, 6379, 443, 6443},  # the Kubernetes API
        "beat": dns | {6379},
        "migrate": dns | {5432},
    }
    if overlay == "dev":
        expected["api"] |= {5000}  # the try-out's local registry
    for name, ports in expected.items():
        assert _ports(rules(objects, CONTROL_PLANE, component(name), "Egress")) == ports, name


def test_the_in_cluster_databases_admit_only_their_clients():
    objects = render("dev")
    clients = {"postgres": {"api", "worker", "migrate"}, "redis": {"api", "worker", "beat"}}
    for name, allowed in clients.items():
        admitted = rules(objects, CONTROL_PLANE, component(name), "Ingress")
        for client in ("api", "worker", "beat", "migrate", "postgres", "redis"):
            reaches = any(
                selects(peer.get("podSelector", {}), component(client))
                and "namespaceSelector" not in peer
                for rule in admitted
                for peer in rule["from"]
            )
            assert reaches == (client in allowed), f"{client} -> {name}"
        assert _ports(rules(objects, CONTROL_PLANE, component(name), "Egress")) == {53}


OPENINGS: dict[str, Json] = {
    "egress to DNS from every pod": {
        "podSelector": {},
        "policyTypes": ["Egress"],
        "egress": [{"ports": [{"protocol": "UDP", "port": 53}]}],
    },
    "egress from evaluations by label": {
        "podSelector": {"matchLabels": {"manieval.io/role": "evaluation"}},
        "policyTypes": ["Egress"],
        "egress": [{"to": [{"ipBlock": {"cidr": "10.0.0.0/8"}}]}],
    },
    "ingress by expression": {
        "podSelector": {
            "matchExpressions": [{"key": "manieval.io/submission", "operator": "Exists"}]
        },
        "policyTypes": ["Ingress"],
        "ingress": [{}],
    },
}


@pytest.mark.parametrize("opening", sorted(OPENINGS))
def test_the_network_check_catches_a_policy_that_opens_evaluation_pods(opening: str):
    policy = {
        "apiVersion": "networking.k8s.io/v1",
        "kind": "NetworkPolicy",
        "metadata": {"name": "opening", "namespace": EVALUATIONS},
        "spec": OPENINGS[opening],
    }
    objects = [*render("production"), policy]
    labels = job_labels(41, 2)
    assert (
        rules(objects, EVALUATIONS, labels, "Egress")
        + rules(objects, EVALUATIONS, labels, "Ingress")
        != []
    )
