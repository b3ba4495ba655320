"""k8s/: every overlay renders, every object is valid for Kubernetes, and old kustomize reads it."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml
from kubernetes_validate.utils import latest_version

from server.models import ACTIVE_STATES, Submission
from tests.deploy.manifests import (
    CONTROL_PLANE,
    EVALUATIONS,
    K8S,
    OVERLAYS,
    REGISTRY_SECRETS,
    SECRETS,
    Json,
    config_maps_read,
    container,
    containers,
    find,
    one,
    pod_templates,
    render,
    secrets_read,
)

VERSIONS = ["1.30", latest_version()]
CRD_GROUPS = ("keda.sh/",)  # custom resources: no official schema, checked by hand below

# What kubectl 1.20's kustomize (v2) reads; newer kustomize reads all of it too.
OLD_KUSTOMIZE_FIELDS = {
    "apiVersion",
    "kind",
    "bases",
    "resources",
    "patchesStrategicMerge",
    "patchesJson6902",
    "images",
    "configMapGenerator",
    "secretGenerator",
    "generatorOptions",
    "commonLabels",
    "commonAnnotations",
    "namePrefix",
    "nameSuffix",
    "namespace",
}


def kustomizations() -> list[Path]:
    return sorted(K8S.rglob("kustomization.yaml"))


def test_every_overlay_is_found():
    assert {"dev", "production", "gvisor"} <= set(OVERLAYS)


@pytest.mark.parametrize("path", kustomizations(), ids=lambda p: str(p.parent.relative_to(K8S)))
def test_kustomizations_use_only_what_old_kustomize_reads(path: Path):
    kustomization = yaml.safe_load(path.read_text())
    assert set(kustomization) <= OLD_KUSTOMIZE_FIELDS
    for entry in kustomization.get("resources", []):
        assert (path.parent / entry).is_file(), f"v2 takes only files in resources: {entry}"
    for entry in kustomization.get("bases", []):
        assert (path.parent / entry / "kustomization.yaml").is_file()
    for entry in kustomization.get("patchesStrategicMerge", []):
        documents = [d for d in yaml.safe_load_all((path.parent / entry).read_text()) if d]
        assert len(documents) == 1, f"{entry}: one patch per file"


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_object_validates_strictly_against_the_official_schema(overlay: str, version: str):
    checked = 0
    for o in render(overlay):
        if o["apiVersion"].startswith(CRD_GROUPS):
            continue
        assert kubernetes_validate.validate(o, version, strict=True), o["metadata"]["name"]
        checked += 1
    assert checked > 20


def test_the_strict_validation_would_catch_a_misspelt_field():
    deployment = one(render("dev"), "Deployment", "manieval-api")
    deployment["spec"]["template"]["spec"]["containers"][0]["readinesProbe"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(deployment, "1.30", strict=True)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_custom_resources_are_only_keda_ones(overlay: str):
    custom = {o["kind"] for o in render(overlay) if o["apiVersion"].startswith(CRD_GROUPS)}
    assert custom <= {"ScaledObject", "TriggerAuthentication"}


def _keys(obj: Json, allowed: set[str], where: str) -> None:
    assert set(obj) <= allowed, f"{where}: unknown fields {sorted(set(obj) - allowed)}"


def _check_scaled_object(o: Json, objects: list[Json]) -> None:
    """KEDA 2.x ScaledObject (keda.sh/v1alpha1), the fields used here, strictly."""
    _keys(o, {"apiVersion", "kind", "metadata", "spec"}, "ScaledObject")
    spec = o["spec"]
    _keys(
        spec,
        {
            "scaleTargetRef",
            "minReplicaCount",
            "maxReplicaCount",
            "pollingInterval",
            "cooldownPeriod",
            "idleReplicaCount",
            "advanced",
            "triggers",
            "fallback",
        },
        "ScaledObject.spec",
    )
    target = spec["scaleTargetRef"]
    _keys(target, {"apiVersion", "kind", "name", "envSourceContainerName"}, "scaleTargetRef")
    assert target.get("kind", "Deployment") == "Deployment"
    one(objects, "Deployment", target["name"])
    for key in ("minReplicaCount", "maxReplicaCount", "pollingInterval"):
        assert isinstance(spec[key], int), key
        assert spec[key] >= 1, key
    assert spec["minReplicaCount"] <= spec["maxReplicaCount"]
    behavior = spec["advanced"]["horizontalPodAutoscalerConfig"]["behavior"]
    _keys(behavior, {"scaleUp", "scaleDown"}, "behavior")
    for trigger in spec["triggers"]:
        _keys(trigger, {"type", "metadata", "authenticationRef", "name"}, "trigger")
        assert all(isinstance(v, str) for v in trigger["metadata"].values()), "strings only"
        auth = one(objects, "TriggerAuthentication", trigger["authenticationRef"]["name"])
        assert auth["metadata"]["namespace"] == o["metadata"]["namespace"]


def _check_trigger_authentication(o: Json) -> None:
    _keys(o, {"apiVersion", "kind", "metadata", "spec"}, "TriggerAuthentication")
    _keys(o["spec"], {"secretTargetRef", "env"}, "TriggerAuthentication.spec")
    for ref in o["spec"]["secretTargetRef"]:
        _keys(ref, {"parameter", "name", "key"}, "secretTargetRef")
        assert ref["parameter"] in {"connection", "password", "host", "userName"}


def scaled_objects() -> list[tuple[str, Json]]:
    return [(overlay, o) for overlay in OVERLAYS for o in find(render(overlay), "ScaledObject")]


def test_keda_objects_have_the_shape_keda_reads():
    found = scaled_objects()
    assert {overlay for overlay, _ in found} == {"production", "gvisor"}
    for overlay, o in found:
        objects = render(overlay)
        assert o["apiVersion"] == "keda.sh/v1alpha1"
        _check_scaled_object(o, objects)
        for auth in find(objects, "TriggerAuthentication"):
            assert auth["apiVersion"] == "keda.sh/v1alpha1"
            _check_trigger_authentication(auth)


def _query_states(query: str) -> tuple[str, set[str]]:
    match = re.fullmatch(
        r"SELECT count\(\*\) FROM (\w+) WHERE state IN \(((?:'\w+'(?:, )?)+)\)", query
    )
    assert match, f"unexpected query: {query}"
    return match.group(1), set(re.findall(r"'(\w+)'", match.group(2)))


def test_workers_scale_on_the_submissions_that_need_a_worker_slot():
    for overlay, o in scaled_objects():
        (trigger,) = o["spec"]["triggers"]
        assert trigger["type"] == "postgresql"
        table, states = _query_states(trigger["metadata"]["query"])
        assert table == Submission.__tablename__
        assert states == {state.value for state in ACTIVE_STATES}
        worker = container(render(overlay), "Deployment", "manieval-worker", "worker")
        concurrency = _concurrency(worker)
        assert int(trigger["metadata"]["targetQueryValue"]) == concurrency, overlay


def test_autoscaled_workers_leave_the_replica_count_to_keda():
    for overlay, o in scaled_objects():
        worker = one(render(overlay), "Deployment", o["spec"]["scaleTargetRef"]["name"])
        assert "replicas" not in worker["spec"], overlay


def _concurrency(worker: Json) -> int:
    argv: list[Any] = [*worker.get("command", []), *worker.get("args", [])]
    return int(argv[argv.index("--concurrency") + 1])


CLUSTER_SCOPED = {
    "Namespace",
    "RuntimeClass",
    "ValidatingAdmissionPolicy",
    "ValidatingAdmissionPolicyBinding",
}
EVALUATION_NAMESPACE_KINDS = {"NetworkPolicy", "ResourceQuota", "LimitRange", "Role", "RoleBinding"}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_evaluation_namespace_holds_only_rules_and_the_rest_is_the_control_plane(
    overlay: str,
):
    for o in render(overlay):
        namespace, kind = o["metadata"].get("namespace"), o["kind"]
        if kind in CLUSTER_SCOPED:
            assert namespace is None
        elif namespace == EVALUATIONS:
            # and the registry's pull credential, which the nodes read for evaluation pods
            pull = (kind, o["metadata"]["name"]) == ("Secret", "manieval-registry-pull")
            assert kind in EVALUATION_NAMESPACE_KINDS or pull, f"{kind} in {EVALUATIONS}"
        else:
            assert namespace == CONTROL_PLANE, f"{kind}/{o['metadata']['name']}"


def missing_references(objects: list[Json], made_by_hand: set[str]) -> list[str]:
    """ConfigMaps, Secrets and ServiceAccounts a pod names that the rendering does not hold
    (a pod naming one that does not exist never starts); Secrets in `made_by_hand` excepted."""
    missing = []

    def held(kind: str, name: str, namespace: str) -> bool:
        return any(o["metadata"].get("namespace") == namespace for o in find(objects, kind, name))

    for workload, template in pod_templates(objects):
        namespace, spec = workload["metadata"]["namespace"], template["spec"]
        where = workload["metadata"]["name"]
        account = spec.get("serviceAccountName", "default")
        if account != "default" and not held("ServiceAccount", account, namespace):
            missing.append(f"{where}: ServiceAccount {account}")
        for c in containers(spec):
            for name in config_maps_read(spec, c["name"]):
                if not held("ConfigMap", name, namespace):
                    missing.append(f"{where}: ConfigMap {name}")
            for name in secrets_read(spec, c["name"]):
                if name not in made_by_hand and not held("Secret", name, namespace):
                    missing.append(f"{where}: Secret {name}")
    return missing


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_everything_a_pod_names_is_in_the_overlay_or_made_by_hand(overlay: str):
    objects = render(overlay)
    # The dev overlay holds its Secrets (and Postgres's); production's are made by hand.
    made_by_hand = set() if overlay == "dev" else set(SECRETS) | set(REGISTRY_SECRETS)
    assert missing_references(objects, made_by_hand) == []
    if overlay != "dev":
        assert missing_references(objects, set()) != [], "the check sees the missing Secrets"
