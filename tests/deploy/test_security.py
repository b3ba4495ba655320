"""k8s/: the isolation ManiEval's threat model rests on (docs/security.md), on every overlay.

Pods meet Pod Security "restricted" field by field, only the worker and the reconciler hold a
token and their Roles are no wider than running (or cleaning up) evaluation Jobs, the workers
and the reconciler hold no database URL and no server secret and reach the server only through
its API, and evaluation pods have no network at all.
"""

from __future__ import annotations

import copy
import re
from typing import Any

import pytest

from tests.deploy.manifests import (
    CONTROL_PLANE,
    EVALUATIONS,
    OPTIONAL_SECRETS,
    OVERLAYS,
    REGISTRY_SECRETS,
    REPO,
    SECRETS,
    Json,
    container,
    containers,
    environment,
    find,
    one,
    pod_templates,
    quantity,
    render,
    secrets_read,
    selects,
)
from tests.worker.test_k8s_manifest import restricted_violations
from worker.kubernetes.manifest import build_network_policy, job_labels

WORKER_MAY = {
    ("batch", "jobs"): {"create", "get", "list", "watch", "delete"},
    ("batch", "jobs/finalizers"): {"update"},  # the Secret's blockOwnerDeletion on its Job
    ("", "pods"): {"list", "watch"},  # followed by watches (worker/kubernetes/informer.py)
    ("", "pods/log"): {"get"},
    ("", "events"): {"list"},
    ("", "secrets"): {"create"},  # each Job's evaluation; never read back
    ("", "resourcequotas"): {"list"},  # room for a Job before creating it
}
RECONCILER_MAY = {("batch", "jobs"): {"get", "list", "delete"}}
# Role (and ServiceAccount, and Deployment) name: what its pods may do in manieval-eval.
ROLES = {"manieval-worker": WORKER_MAY, "manieval-reconciler": RECONCILER_MAY}
# (Deployment, container) of the pods that run participants' work next to untrusted code.
WORKERS = [("manieval-worker", "worker"), ("manieval-reconciler", "reconciler")]
SERVER_ONLY = {"MANIEVAL_DATABASE_URL", "MANIEVAL_SECRET_KEY", "MANIEVAL_SEED_SECRET"}
WORKER_SECRET_KEYS = {"MANIEVAL_WORKER_TOKEN", "MANIEVAL_BROKER_URL"}


def account(name: str) -> Json:
    return {"kind": "ServiceAccount", "name": name, "namespace": CONTROL_PLANE}


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
def test_only_the_worker_and_the_reconciler_hold_a_service_account_token(overlay: str):
    objects = render(overlay)
    holders = {
        workload["metadata"]["name"]
        for workload, template in pod_templates(objects)
        if _token_mounted(objects, template["spec"], workload["metadata"]["namespace"])
    }
    assert holders == set(ROLES)
    for sa in find(objects, "ServiceAccount"):
        assert sa.get("automountServiceAccountToken") is False, sa["metadata"]["name"]
    for name in ROLES:  # each its own account, bound to its own Role
        spec = one(objects, "Deployment", name)["spec"]["template"]["spec"]
        assert spec["serviceAccountName"] == name


def rbac_problems(objects: list[Json]) -> list[str]:
    """Every way the RBAC objects grant more than running evaluation Jobs (the worker) and
    looking at and deleting them (the reconciler)."""
    problems = [f"{o['kind']} {o['metadata']['name']}" for o in objects if "Cluster" in o["kind"]]
    roles = find(objects, "Role")
    if sorted((r["metadata"]["name"], r["metadata"]["namespace"]) for r in roles) != sorted(
        (name, EVALUATIONS) for name in ROLES
    ):
        problems.append(f"roles: {[r['metadata'] for r in roles]}")
    for role in roles:
        may = ROLES.get(role["metadata"]["name"], {})
        for rule in role["rules"]:
            if set(rule) - {"apiGroups", "resources", "verbs"}:
                problems.append(f"rule with {sorted(set(rule))}")
            for group in rule.get("apiGroups", []):
                for resource in rule.get("resources", []):
                    extra = set(rule["verbs"]) - may.get((group, resource), set())
                    if extra:
                        problems.append(f"{group}/{resource}: {sorted(extra)}")
    for binding in find(objects, "RoleBinding"):
        name = binding["metadata"]["name"]
        if (
            name not in ROLES
            or binding["metadata"]["namespace"] != EVALUATIONS
            or binding["roleRef"]
            != {"apiGroup": "rbac.authorization.k8s.io", "kind": "Role", "name": name}
            or binding["subjects"] != [account(name)]
        ):
            problems.append(f"binding {name}")
    return problems


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_worker_and_reconciler_may_only_handle_jobs_in_the_evaluation_namespace(
    overlay: str,
):
    objects = render(overlay)
    assert rbac_problems(objects) == []
    assert sorted(b["metadata"]["name"] for b in find(objects, "RoleBinding")) == sorted(ROLES)


WIDER: dict[str, Any] = {
    "a wildcard verb": lambda roles: roles["manieval-worker"]["rules"][0].update(verbs=["*"]),
    "a wildcard resource": lambda roles: roles["manieval-worker"]["rules"][1].update(
        resources=["*"]
    ),
    "secrets": lambda roles: roles["manieval-worker"]["rules"].append(
        {"apiGroups": [""], "resources": ["secrets"], "verbs": ["get"]}
    ),
    "pods/exec": lambda roles: roles["manieval-worker"]["rules"][2].update(
        resources=["pods/log", "pods/exec"]
    ),
    "patching jobs": lambda roles: roles["manieval-worker"]["rules"][0]["verbs"].append("patch"),
    "watching events": lambda roles: roles["manieval-worker"]["rules"][3]["verbs"].append("watch"),
    "deleting pods": lambda roles: roles["manieval-worker"]["rules"][1]["verbs"].append("delete"),
    "reading secrets": lambda roles: roles["manieval-worker"]["rules"][4]["verbs"].append("get"),
    "another namespace": lambda roles: roles["manieval-worker"]["metadata"].update(
        namespace="default"
    ),
    "a reconciler creating jobs": lambda roles: roles["manieval-reconciler"]["rules"][0][
        "verbs"
    ].append("create"),
    "a reconciler reading logs": lambda roles: roles["manieval-reconciler"]["rules"].append(
        {"apiGroups": [""], "resources": ["pods/log"], "verbs": ["get"]}
    ),
    "a reconciler in another namespace": lambda roles: roles["manieval-reconciler"][
        "metadata"
    ].update(namespace=CONTROL_PLANE),
}


@pytest.mark.parametrize("change", sorted(WIDER))
def test_the_rbac_check_catches_a_wider_role(change: str):
    objects = copy.deepcopy(render("production"))
    WIDER[change]({name: one(objects, "Role", name) for name in ROLES})
    assert rbac_problems(objects) != []


def test_the_rbac_check_catches_a_cluster_role():
    objects = copy.deepcopy(render("production"))
    role = copy.deepcopy(one(objects, "Role", "manieval-worker"))
    role["kind"] = "ClusterRole"
    assert rbac_problems([*objects, role]) != []


def test_the_rbac_check_catches_the_reconciler_bound_to_the_workers_role():
    objects = copy.deepcopy(render("production"))
    one(objects, "RoleBinding", "manieval-reconciler")["roleRef"]["name"] = "manieval-worker"
    assert rbac_problems(objects) != []


def secret_keys(objects: list[Json], pod_spec: Json, container_name: str) -> set[str]:
    """The keys of every Secret a container can read (a Secret made by hand: what SECRETS says
    it holds); `?NAME` for a Secret of unknown contents."""
    keys: set[str] = set()
    for name in secrets_read(pod_spec, container_name):
        rendered = [
            o for o in find(objects, "Secret", name) if o["metadata"]["namespace"] == CONTROL_PLANE
        ]
        if rendered:
            keys |= {k for o in rendered for k in [*o.get("stringData", {}), *o.get("data", {})]}
        elif name in SECRETS:
            keys |= SECRETS[name] | OPTIONAL_SECRETS.get(name, set())
        else:
            keys.add(f"?{name}")
    return keys


def keys_read(objects: list[Json], pod_spec: Json, container_name: str) -> set[str]:
    """Every setting a container can read: its ConfigMaps', its Secrets' and its own env."""
    c = next(c for c in containers(pod_spec) if c["name"] == container_name)
    keys = {e["name"] for e in c.get("env", [])} | secret_keys(objects, pod_spec, container_name)
    for source in c.get("envFrom", []):
        if "configMapRef" in source:
            for o in find(objects, "ConfigMap", source["configMapRef"]["name"]):
                if o["metadata"]["namespace"] == CONTROL_PLANE:
                    keys |= set(o.get("data", {}))
    return keys


def worker_secret_problems(objects: list[Json]) -> list[str]:
    """Every way a worker or the reconciler could read the database URL or a server secret."""
    problems = []
    for name, container_name in WORKERS:
        spec = one(objects, "Deployment", name)["spec"]["template"]["spec"]
        read = secrets_read(spec, container_name)
        if read != {"manieval-worker-secrets"}:
            problems.append(f"{name} reads the Secrets {sorted(read)}")
        keys = keys_read(objects, spec, container_name)
        problems += [f"{name} reads {key}" for key in sorted(keys & SERVER_ONLY)]
        problems += [f"{name} reads {key}" for key in sorted(keys) if key.startswith("?")]
    return problems


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_workers_and_the_reconciler_hold_no_database_url_and_no_server_secret(overlay: str):
    objects = render(overlay)
    assert worker_secret_problems(objects) == []
    for name, container_name in WORKERS:
        spec = one(objects, "Deployment", name)["spec"]["template"]["spec"]
        assert secret_keys(objects, spec, container_name) == WORKER_SECRET_KEYS, name


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_api_and_the_migration_read_only_their_secrets(overlay: str):
    objects = render(overlay)
    api = one(objects, "Deployment", "manieval-api")["spec"]["template"]["spec"]
    assert secrets_read(api, "api") == {
        "manieval-secrets",
        "manieval-db",
        "manieval-registry-signing",
    }
    migrate = one(objects, "Job", "manieval-migrate")["spec"]["template"]["spec"]
    assert secrets_read(migrate, "migrate") == {"manieval-db"}
    assert keys_read(objects, migrate, "migrate") == {"MANIEVAL_DATABASE_URL"}
    for workload, template in pod_templates(objects):  # no ManiEval pod reads another Secret
        for c in containers(template["spec"]):
            if not c["image"].startswith("docker.io/library/"):  # Postgres, Redis
                read = secrets_read(template["spec"], c["name"])
                assert read <= set(SECRETS) | set(REGISTRY_SECRETS), workload["metadata"]["name"]


def test_the_dev_secrets_hold_what_each_pod_needs_and_the_worker_token_agrees():
    objects = render("dev")
    for name, keys in SECRETS.items():
        (secret,) = find(objects, "Secret", name)
        assert set(secret["stringData"]) == keys, name
    token = {
        name: one(objects, "Secret", name)["stringData"]["MANIEVAL_WORKER_TOKEN"]
        for name in ("manieval-secrets", "manieval-worker-secrets")
    }
    assert len(set(token.values())) == 1, "the workers present the token the server checks"
    broker = {
        name: one(objects, "Secret", name)["stringData"]["MANIEVAL_BROKER_URL"]
        for name in ("manieval-secrets", "manieval-worker-secrets")
    }
    assert len(set(broker.values())) == 1, "the server sends wake-ups where the workers listen"
    for name, container_name in WORKERS:
        env = environment(objects, one(objects, "Deployment", name), container_name)
        assert env["MANIEVAL_WORKER_TOKEN"] == token["manieval-secrets"], name


def documented_secrets() -> dict[str, set[str]]:
    """The Secrets docs/deploy.md tells production to create, and the keys of each."""
    text = (REPO / "docs" / "deploy.md").read_text().replace("\\\n", " ")
    found: dict[str, set[str]] = {}
    for command in re.findall(r"kubectl -n manieval create secret generic ([^\n]+)", text):
        name = command.split()[0]
        found[name] = set(re.findall(r"--from-literal=(\w+)=", command))
    return found


def test_production_is_told_to_make_each_secret_with_the_keys_its_pods_read():
    documented = documented_secrets()
    for name, keys in SECRETS.items():
        assert keys <= documented[name] <= keys | OPTIONAL_SECRETS.get(name, set()), name


WORKER_GIVEN: dict[str, Any] = {
    "the server's Secret": lambda objects: container(
        objects, "Deployment", "manieval-worker", "worker"
    )["envFrom"].append({"secretRef": {"name": "manieval-secrets"}}),
    "the database URL, one key": lambda objects: container(
        objects, "Deployment", "manieval-reconciler", "reconciler"
    )["env"].append(
        {
            "name": "MANIEVAL_DATABASE_URL",
            "valueFrom": {"secretKeyRef": {"name": "manieval-db", "key": "MANIEVAL_DATABASE_URL"}},
        }
    ),
    "a mounted Secret": lambda objects: one(objects, "Deployment", "manieval-reconciler")["spec"][
        "template"
    ]["spec"]["volumes"].append({"name": "s", "secret": {"secretName": "manieval-secrets"}}),
    "a Secret of unknown contents": lambda objects: container(
        objects, "Deployment", "manieval-worker", "worker"
    )["envFrom"].append({"secretRef": {"name": "something-else"}}),
    "a secret in its ConfigMap": lambda objects: one(
        objects, "ConfigMap", "manieval-worker-config"
    )["data"].update(MANIEVAL_SEED_SECRET="x" * 40),
    "a secret in its own env": lambda objects: container(
        objects, "Deployment", "manieval-worker", "worker"
    )["env"].append({"name": "MANIEVAL_SECRET_KEY", "value": "x" * 40}),
}


@pytest.mark.parametrize("change", sorted(WORKER_GIVEN))
def test_the_secret_check_catches_a_worker_given_a_server_secret(change: str):
    objects = copy.deepcopy(render("production"))
    WORKER_GIVEN[change](objects)
    assert worker_secret_problems(objects) != []


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


def opened(
    rule_list: list[Json], key: str, peer_labels: dict[str, str], peer_namespace: str, home: str
) -> set[int | str]:
    """The ports `rule_list` (ingress rules, key "from"; egress rules, key "to") of a policy in
    namespace `home` open to or from a pod with `peer_labels` in `peer_namespace`; "all" for
    every port. An ipBlock is taken to match every address, pods' included."""
    namespace_labels = {"kubernetes.io/metadata.name": peer_namespace}
    ports: set[int | str] = set()
    for rule in rule_list:
        peers = rule.get(key)
        matched = not peers or any(
            "ipBlock" in peer
            or (
                selects(peer.get("podSelector", {}), peer_labels)
                and (
                    selects(peer["namespaceSelector"], namespace_labels)
                    if "namespaceSelector" in peer
                    else peer_namespace == home
                )
            )
            for peer in peers
        )
        if matched:
            ports |= {p["port"] for p in rule["ports"]} if rule.get("ports") else {"all"}
    return ports


INGRESS_CONTROLLER = ({"app.kubernetes.io/name": "ingress-nginx"}, "ingress-nginx")


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_api_admits_only_the_ingress_controller_the_workers_and_the_reconciler(
    overlay: str,
):
    objects = render(overlay)
    api_in = rules(objects, CONTROL_PLANE, component("api"), "Ingress")
    expected: dict[str, set[int | str]] = {"worker": {8000}, "reconciler": {8000}}
    for name in ("api", "migrate", "postgres", "redis", "worker", "reconciler", "registry"):
        ports = opened(api_in, "from", component(name), CONTROL_PLANE, CONTROL_PLANE)
        assert ports == expected.get(name, set()), name
    assert opened(api_in, "from", *INGRESS_CONTROLLER, CONTROL_PLANE) == {8000}
    # Nothing else: not the evaluations (participants' code), nor another namespace.
    evaluation = {**job_labels(41, 2), "batch.kubernetes.io/job-completion-index": "0"}
    assert opened(api_in, "from", evaluation, EVALUATIONS, CONTROL_PLANE) == set()
    assert opened(api_in, "from", component("worker"), "default", CONTROL_PLANE) == set()
    for name in ("worker", "reconciler", "migrate"):
        assert rules(objects, CONTROL_PLANE, component(name), "Ingress") == [], name


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_control_plane_pods_reach_only_what_they_need(overlay: str):
    objects = render(overlay)
    dns = {53}
    workers = dns | {6379, 443, 6443, 8000}  # Redis, the Kubernetes API, the server's API
    expected = {
        # registries, pinning tags to digests: others over HTTPS, the service's own on 5000
        "api": dns | {5432, 6379, 443, 5000},
        "worker": workers,
        "reconciler": workers,
        "migrate": dns | {5432},
        "registry": dns,  # it verifies tokens itself
    }
    for name, ports in expected.items():
        assert _ports(rules(objects, CONTROL_PLANE, component(name), "Egress")) == ports, name


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_workers_reach_the_api_pods_on_their_port_and_no_other_pod_on_it(overlay: str):
    objects = render(overlay)
    api = container(objects, "Deployment", "manieval-api", "api")
    (port,) = [p["containerPort"] for p in api["ports"] if p["name"] == "http"]
    for name in ("worker", "reconciler"):
        out = rules(objects, CONTROL_PLANE, component(name), "Egress")
        assert port in opened(out, "to", component("api"), CONTROL_PLANE, CONTROL_PLANE), name
        for other in ("postgres", "redis", "worker", "reconciler", "migrate"):
            reached = opened(out, "to", component(other), CONTROL_PLANE, CONTROL_PLANE)
            assert port not in reached, f"{name} -> {other}"
            assert 5432 not in reached, f"{name} -> {other}: they have no database"


def test_the_in_cluster_databases_admit_only_their_clients():
    objects = render("dev")
    clients = {"postgres": {"api", "migrate"}, "redis": {"api", "worker", "reconciler"}}
    for name, allowed in clients.items():
        admitted = rules(objects, CONTROL_PLANE, component(name), "Ingress")
        for client in ("api", "worker", "reconciler", "migrate", "postgres", "redis"):
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
