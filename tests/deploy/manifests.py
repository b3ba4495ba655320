"""The k8s/ overlays as the objects they render to, and ways of looking at them.

Rendering uses the kustomize built into kubectl (`kubectl kustomize DIR`), the tool an operator
applies them with. Without kubectl the tests that need a rendering fail in CI and skip elsewhere.
"""

from __future__ import annotations

import copy
import functools
import os
import shutil
import subprocess
from collections.abc import Iterator, Mapping
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
import yaml
from kubernetes.utils.quantity import parse_quantity

REPO = Path(__file__).resolve().parents[2]
K8S = REPO / "k8s"
OVERLAYS = sorted(p.parent.name for p in (K8S / "overlays").glob("*/kustomization.yaml"))
CONTROL_PLANE, EVALUATIONS = "manieval", "manieval-eval"
KUBECTL = shutil.which("kubectl") or "/usr/bin/kubectl"
INSTALL_HINT = "apt-get install -y kubernetes-client (or any kubectl with kustomize)"

Json = dict[str, Any]
WORKLOADS = {"Deployment", "StatefulSet", "DaemonSet", "ReplicaSet", "Job"}

# The Secrets ManiEval's pods read and what each holds: the dev overlay renders them with public
# values, production makes them by hand (docs/deploy.md, "Secrets"). The worker token is in two:
# the server checks it, the workers present it (and a rotation changes them one after the other).
SECRETS = {
    "manieval-secrets": {
        "MANIEVAL_SECRET_KEY",
        "MANIEVAL_SEED_SECRET",
        "MANIEVAL_WORKER_TOKEN",
        "MANIEVAL_BROKER_URL",
        "MANIEVAL_REDIS_URL",
        "MANIEVAL_REGISTRY_PULL_PASSWORD",
    },
    "manieval-db": {"MANIEVAL_DATABASE_URL"},
    "manieval-worker-secrets": {"MANIEVAL_WORKER_TOKEN", "MANIEVAL_BROKER_URL"},
}
OPTIONAL_SECRETS = {"manieval-secrets": {"MANIEVAL_METRICS_TOKEN"}}
"""Keys a Secret made by hand may hold beyond the dev overlay's."""
# The service's own registry's Secrets (k8s/base/registry.yaml): (namespace, type, keys).
REGISTRY_SECRETS = {
    "manieval-registry-signing": ("manieval", "kubernetes.io/tls", {"tls.crt", "tls.key"}),
    "manieval-registry-pull": (
        "manieval-eval",
        "kubernetes.io/dockerconfigjson",
        {".dockerconfigjson"},
    ),
}


def require_kubectl() -> str:
    """kubectl's path; fail in CI, skip elsewhere, when it is missing."""
    if os.access(KUBECTL, os.X_OK):
        return KUBECTL
    problem = f"kubectl is not installed ({INSTALL_HINT})"
    if os.environ.get("CI") == "true":
        pytest.fail(problem)
    pytest.skip(problem)


@functools.cache
def _render(directory: Path) -> tuple[Json, ...]:
    done = subprocess.run(
        [KUBECTL, "kustomize", str(directory)], capture_output=True, text=True, timeout=120
    )
    if done.returncode != 0:
        pytest.fail(f"kubectl kustomize {directory} failed:\n{done.stderr}")
    return tuple(doc for doc in yaml.safe_load_all(done.stdout) if doc)


def render(overlay: str) -> list[Json]:
    """The objects `kubectl kustomize k8s/overlays/OVERLAY` produces (fresh copies)."""
    require_kubectl()
    return copy.deepcopy(list(_render(K8S / "overlays" / overlay)))


def find(objects: list[Json], kind: str, name: str | None = None) -> list[Json]:
    """The objects of `kind` (and `name`)."""
    return [
        o for o in objects if o["kind"] == kind and (name is None or o["metadata"]["name"] == name)
    ]


def one(objects: list[Json], kind: str, name: str) -> Json:
    """The single object of this kind and name."""
    found = find(objects, kind, name)
    assert len(found) == 1, f"expected one {kind}/{name}, found {len(found)}"
    return found[0]


def pod_templates(objects: list[Json]) -> Iterator[tuple[Json, Json]]:
    """(workload, pod template) of every workload."""
    for o in objects:
        if o["kind"] in WORKLOADS:
            yield o, o["spec"]["template"]


def containers(pod_spec: Json) -> list[Json]:
    """Init, regular and ephemeral containers of a pod spec."""
    return [
        *pod_spec.get("initContainers", []),
        *pod_spec["containers"],
        *pod_spec.get("ephemeralContainers", []),
    ]


def container(objects: list[Json], kind: str, name: str, container_name: str) -> Json:
    """One container of one workload."""
    spec = one(objects, kind, name)["spec"]["template"]["spec"]
    return next(c for c in containers(spec) if c["name"] == container_name)


def selects(selector: Mapping[str, Any], labels: Mapping[str, str]) -> bool:
    """Whether a LabelSelector matches these labels (the empty selector matches everything)."""
    for key, value in selector.get("matchLabels", {}).items():
        if labels.get(key) != value:
            return False
    for expression in selector.get("matchExpressions", []):
        key, operator = expression["key"], expression["operator"]
        values = expression.get("values", [])
        present = key in labels
        if operator == "In" and not (present and labels[key] in values):
            return False
        if operator == "NotIn" and present and labels[key] in values:
            return False
        if operator == "Exists" and not present:
            return False
        if operator == "DoesNotExist" and present:
            return False
    return True


def quantity(value: str | int | float) -> Decimal:
    """A Kubernetes quantity as a number (cpu in cores, memory in bytes)."""
    result: Decimal = parse_quantity(value)
    return result


def environment(objects: list[Json], workload: Json, container_name: str) -> dict[str, str]:
    """A container's environment: its ConfigMaps and Secrets (envFrom), then its own env. A
    value taken from a Secret that is not rendered (production's are made by hand) is missing;
    one taken from the pod (the downward API) is a stand-in: the pod's name is
    `<workload>-pod`."""
    spec = workload["spec"]["template"]["spec"]
    c = next(c for c in containers(spec) if c["name"] == container_name)
    namespace = workload["metadata"]["namespace"]
    env: dict[str, str] = {}
    for source in c.get("envFrom", []):
        if "configMapRef" in source:
            found = find(objects, "ConfigMap", source["configMapRef"]["name"])
            env.update(
                data for o in found if _in(o, namespace) for data in o.get("data", {}).items()
            )
        if "secretRef" in source:
            for o in find(objects, "Secret", source["secretRef"]["name"]):
                if _in(o, namespace):
                    env.update(o.get("stringData", {}))
    for e in c.get("env", []):
        if "value" in e:
            env[e["name"]] = e["value"]
        elif "secretKeyRef" in e.get("valueFrom", {}):
            ref = e["valueFrom"]["secretKeyRef"]
            for o in find(objects, "Secret", ref["name"]):
                if _in(o, namespace) and ref["key"] in o.get("stringData", {}):
                    env[e["name"]] = o["stringData"][ref["key"]]
        elif "fieldRef" in e.get("valueFrom", {}):
            env[e["name"]] = _from_pod(workload, e["valueFrom"]["fieldRef"]["fieldPath"])
    return env


def _from_pod(workload: Json, path: str) -> str:
    if path == "metadata.name":
        return f"{workload['metadata']['name']}-pod"
    if path == "metadata.namespace":
        return str(workload["metadata"]["namespace"])
    raise AssertionError(f"no stand-in for the pod's {path}")


def secrets_read(pod_spec: Json, container_name: str) -> set[str]:
    """The names of the Secrets a container can read: through its environment (envFrom, or one
    key at a time) or a volume of its pod (mounted or not: any container may mount it)."""
    c = next(c for c in containers(pod_spec) if c["name"] == container_name)
    names = {s["secretRef"]["name"] for s in c.get("envFrom", []) if "secretRef" in s}
    names |= {
        e["valueFrom"]["secretKeyRef"]["name"]
        for e in c.get("env", [])
        if "secretKeyRef" in e.get("valueFrom", {})
    }
    for volume in pod_spec.get("volumes", []):
        if "secret" in volume:
            names.add(volume["secret"]["secretName"])
        for source in volume.get("projected", {}).get("sources", []):
            if "secret" in source:
                names.add(source["secret"]["name"])
    return names


def config_maps_read(pod_spec: Json, container_name: str) -> set[str]:
    """The names of the ConfigMaps a container reads, as secrets_read does for Secrets."""
    c = next(c for c in containers(pod_spec) if c["name"] == container_name)
    names = {s["configMapRef"]["name"] for s in c.get("envFrom", []) if "configMapRef" in s}
    names |= {
        e["valueFrom"]["configMapKeyRef"]["name"]
        for e in c.get("env", [])
        if "configMapKeyRef" in e.get("valueFrom", {})
    }
    for volume in pod_spec.get("volumes", []):
        if "configMap" in volume:
            names.add(volume["configMap"]["name"])
        for source in volume.get("projected", {}).get("sources", []):
            if "configMap" in source:
                names.add(source["configMap"]["name"])
    return names


def argv(c: Json) -> list[str]:
    """A container's command line: its command, then its args."""
    return [str(word) for word in [*c.get("command", []), *c.get("args", [])]]


def option(words: list[str], *names: str) -> list[str]:
    """Every value given to a command-line option (`-Q x`, `--queues x` or `--queues=x`)."""
    values = []
    for i, word in enumerate(words):
        for name in names:
            if word == name and i + 1 < len(words):
                values.append(words[i + 1])
            elif name.startswith("--") and word.startswith(name + "="):
                values.append(word.split("=", 1)[1])
    return values


def _in(o: Json, namespace: str) -> bool:
    return bool(o["metadata"].get("namespace") == namespace)
