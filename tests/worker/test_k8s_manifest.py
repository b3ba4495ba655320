"""The evaluation Job manifest: valid for the official schemas, restricted, and deterministic."""

from __future__ import annotations

import copy
import json
import math
import re
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any

import kubernetes_validate
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from kubernetes_validate.utils import latest_version

from evaluator.job import ENDPOINT_DIR, JOB_SPEC_ENV, JOB_SPEC_FILE_ENV, SHARDS_ENV, EvaluationJob
from internal_api.schemas import Assignment
from manieval_sdk.serve import ENDPOINT_ENV
from server.kit.settings import Settings
from testkit.workers import worker_settings
from tests.worker.k8s_specs import (
    TINY_SUITE,
    make_spec,
    tiny_evaluation,
)
from worker.containers import ContainerLimits, container_config
from worker.deadline import wall_clock_limit_s
from worker.kubernetes.manifest import (
    GPU_RESOURCE,
    MAX_PAYLOAD_BYTES,
    POLICY_UID,
    JobSpec,
    Resources,
    active_deadline_for,
    build_job,
    build_network_policy,
    build_secret,
)
from worker.kubernetes.quota import demand
from worker.kubernetes.spec import job_spec

Json = dict[str, Any]
VERSIONS = ["1.30", latest_version()]
GPU_POOL: Json = {
    "gpu_node_selector": (("cloud.google.com/gke-accelerator", "nvidia-l4"),),
    "gpu_tolerations": (
        (("key", "nvidia.com/gpu"), ("operator", "Exists"), ("effect", "NoSchedule")),
    ),
}


def gpu_policy_evaluation(gpus: int = 1) -> EvaluationJob:
    """The tiny evaluation, its suite giving each policy `gpus` GPUs."""
    suite = TINY_SUITE.read_text() + f"policy: {{gpus: {gpus}}}\n"
    return tiny_evaluation().model_copy(update={"suite_yaml": suite})


VARIANTS: dict[str, Json] = {
    "one-pod": {},
    "indexed": {"shards": 3},
    "gpu": {"gpu": True},
    "gvisor": {"runtime_class_name": "gvisor"},
    "policy-gpus": {"policy_gpus": 2, "evaluation": gpu_policy_evaluation(2), **GPU_POOL},
    "indexed-gpu-gvisor": {"shards": 4, "gpu": True, "runtime_class_name": "gvisor"},
    "node-pool": {
        "node_selector": (("manieval.io/pool", "eval"), ("kubernetes.io/arch", "amd64")),
        "tolerations": (
            (("key", "manieval.io/eval"), ("operator", "Exists"), ("effect", "NoSchedule")),
            (
                ("key", "gpu"),
                ("operator", "Equal"),
                ("value", "true"),
                ("effect", "NoExecute"),
                ("tolerationSeconds", 60),
            ),
        ),
        "priority_class_name": "manieval-eval",
        "image_pull_secrets": ("registry-pull", "mirror-pull"),
        "runtime_class_name": "gvisor",
    },
}

# Pod Security Standards, "restricted" (which includes "baseline"), as of Kubernetes 1.30.
RESTRICTED_VOLUMES = {
    "configMap",
    "csi",
    "downwardAPI",
    "emptyDir",
    "ephemeral",
    "persistentVolumeClaim",
    "projected",
    "secret",
}
SAFE_SYSCTLS = {
    "kernel.shm_rmid_forced",
    "net.ipv4.ip_local_port_range",
    "net.ipv4.ip_unprivileged_port_start",
    "net.ipv4.tcp_syncookies",
    "net.ipv4.ping_group_range",
    "net.ipv4.ip_local_reserved_ports",
    "net.ipv4.tcp_keepalive_time",
    "net.ipv4.tcp_fin_timeout",
    "net.ipv4.tcp_keepalive_intvl",
    "net.ipv4.tcp_keepalive_probes",
}
SELINUX_TYPES = {"", "container_t", "container_init_t", "container_kvm_t", "container_engine_t"}


def pod_of(manifest: Json) -> Json:
    spec: Json = manifest["spec"]["template"]["spec"]
    return spec


def containers_of(pod: Json) -> list[Json]:
    return [*pod.get("initContainers", []), *pod["containers"], *pod.get("ephemeralContainers", [])]


def container(manifest: Json, name: str) -> Json:
    return next(c for c in containers_of(pod_of(manifest)) if c["name"] == name)


def restricted_violations(pod: Json) -> list[str]:
    """Every way `pod` breaks the restricted profile (and our stricter rules), field by field."""
    problems = []
    pod_sc = pod.get("securityContext", {})
    for key in ("hostNetwork", "hostPID", "hostIPC"):
        if pod.get(key):
            problems.append(f"pod: {key}")
    problems += _selinux_and_windows("pod", pod_sc)
    if pod_sc.get("runAsUser") == 0:
        problems.append("pod: runAsUser 0")
    if pod_sc.get("seccompProfile", {}).get("type") == "Unconfined":
        problems.append("pod: seccomp Unconfined")
    if pod_sc.get("appArmorProfile", {}).get("type") not in (None, "RuntimeDefault", "Localhost"):
        problems.append("pod: AppArmor profile")
    for sysctl in pod_sc.get("sysctls", []):
        if sysctl["name"] not in SAFE_SYSCTLS:
            problems.append(f"pod: sysctl {sysctl['name']}")
    for volume in pod.get("volumes", []):
        kinds = set(volume) - {"name"}
        if kinds - RESTRICTED_VOLUMES:
            problems.append(f"volume {volume['name']}: type {sorted(kinds)}")
    for c in containers_of(pod):
        problems += [f"{c['name']}: {p}" for p in _container_violations(c, pod_sc)]
    return problems


def _container_violations(c: Json, pod_sc: Json) -> list[str]:
    sc = c.get("securityContext", {})
    problems = _selinux_and_windows("container", sc)
    if sc.get("privileged"):
        problems.append("privileged")
    if any(port.get("hostPort") for port in c.get("ports", [])):
        problems.append("hostPort")
    if sc.get("procMount", "Default") != "Default":
        problems.append("procMount")
    if sc.get("allowPrivilegeEscalation") is not False:
        problems.append("allowPrivilegeEscalation is not false")
    if sc.get("runAsNonRoot", pod_sc.get("runAsNonRoot")) is not True:
        problems.append("runAsNonRoot is not true")
    uid = sc.get("runAsUser", pod_sc.get("runAsUser"))
    if uid is None or uid == 0:
        problems.append(f"runAsUser is {uid} (an explicit non-zero uid is required)")
    seccomp = sc.get("seccompProfile", pod_sc.get("seccompProfile", {})).get("type")
    if seccomp not in ("RuntimeDefault", "Localhost"):
        problems.append(f"seccomp profile {seccomp}")
    if sc.get("appArmorProfile", {}).get("type") not in (None, "RuntimeDefault", "Localhost"):
        problems.append("AppArmor profile")
    capabilities = sc.get("capabilities", {})
    if "ALL" not in capabilities.get("drop", []):
        problems.append("capabilities do not drop ALL")
    if capabilities.get("add"):
        problems.append(f"capabilities added: {capabilities['add']}")
    if sc.get("readOnlyRootFilesystem") is not True:
        problems.append("root filesystem is writable")
    return problems


def _selinux_and_windows(where: str, sc: Json) -> list[str]:
    problems = []
    selinux = sc.get("seLinuxOptions", {})
    if selinux.get("type", "") not in SELINUX_TYPES or selinux.get("user") or selinux.get("role"):
        problems.append(f"{where}: SELinux options")
    if sc.get("windowsOptions", {}).get("hostProcess"):
        problems.append(f"{where}: hostProcess")
    return problems


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_every_manifest_variant_validates_strictly_against_the_official_schema(
    variant: str, version: str
):
    manifest = build_job(make_spec(**VARIANTS[variant]))
    assert kubernetes_validate.validate(manifest, version, strict=True)


@pytest.mark.parametrize("version", VERSIONS)
def test_the_network_policy_validates_strictly(version: str):
    assert kubernetes_validate.validate(build_network_policy("evals"), version, strict=True)


def test_the_strict_validation_would_catch_an_unknown_field():
    manifest = build_job(make_spec())
    pod_of(manifest)["containers"][0]["securityContex"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(manifest, "1.30", strict=True)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_every_manifest_variant_satisfies_the_restricted_profile(variant: str):
    assert restricted_violations(pod_of(build_job(make_spec(**VARIANTS[variant])))) == []


def _parent(pod: Json, path: str) -> tuple[Any, Any]:
    *parents, last = path.split(".")
    target: Any = pod
    for part in parents:
        target = target[int(part)] if part.isdigit() else target.setdefault(part, {})
    return target, int(last) if last.isdigit() else last


def _set(path: str, value: Any) -> Callable[[Json], None]:
    def apply(pod: Json) -> None:
        target, key = _parent(pod, path)
        target[key] = value

    return apply


def _drop(*paths: str) -> Callable[[Json], None]:
    def apply(pod: Json) -> None:
        for path in paths:
            target, key = _parent(pod, path)
            target.pop(key, None)

    return apply


MUTATIONS: dict[str, Callable[[Json], None]] = {
    "host network": _set("hostNetwork", True),
    "host pid": _set("hostPID", True),
    "privileged": _set("initContainers.0.securityContext.privileged", True),
    "added capability": _set("containers.0.securityContext.capabilities.add", ["SYS_ADMIN"]),
    "drop not ALL": _set("containers.0.securityContext.capabilities.drop", ["NET_RAW"]),
    "escalation allowed": _drop("initContainers.0.securityContext.allowPrivilegeEscalation"),
    "root uid": _set("initContainers.0.securityContext.runAsUser", 0),
    "no uid": _drop("containers.0.securityContext.runAsUser"),
    "root allowed": _drop(
        "securityContext.runAsNonRoot", "containers.0.securityContext.runAsNonRoot"
    ),
    "no seccomp": _drop(
        "securityContext.seccompProfile", "containers.0.securityContext.seccompProfile"
    ),
    "unconfined": _set("securityContext.seccompProfile", {"type": "Unconfined"}),
    "writable root": _set("containers.0.securityContext.readOnlyRootFilesystem", False),
    "host path": _set("volumes.1", {"name": "scratch", "hostPath": {"path": "/"}}),
    "host port": _set("containers.0.ports", [{"containerPort": 80, "hostPort": 80}]),
    "unsafe sysctl": _set("securityContext.sysctls", [{"name": "kernel.msgmax", "value": "1"}]),
}


@pytest.mark.parametrize("mutation", sorted(MUTATIONS))
def test_the_restricted_check_reports_each_kind_of_violation(mutation: str):
    pod = copy.deepcopy(pod_of(build_job(make_spec())))
    MUTATIONS[mutation](pod)
    assert restricted_violations(pod) != []


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_requests_equal_limits_for_every_container(variant: str):
    for c in containers_of(pod_of(build_job(make_spec(**VARIANTS[variant])))):
        resources = c["resources"]
        assert resources["requests"] == resources["limits"]
        assert {"cpu", "memory", "ephemeral-storage"} <= set(resources["limits"])


def test_a_gpu_is_requested_and_limited_for_the_evaluator_only():
    manifest = build_job(make_spec(gpu=True))
    assert container(manifest, "evaluator")["resources"]["limits"][GPU_RESOURCE] == "1"
    assert container(manifest, "evaluator")["resources"]["requests"][GPU_RESOURCE] == "1"
    assert GPU_RESOURCE not in container(manifest, "policy")["resources"]["limits"]
    no_gpu = build_job(make_spec())
    assert all(GPU_RESOURCE not in c["resources"]["limits"] for c in containers_of(pod_of(no_gpu)))


def test_a_suite_that_simulates_on_the_gpu_needs_gpu_set():
    cuda = TINY_SUITE.read_text().replace(
        "{env_id: PickCube-v1,", "{env_id: PickCube-v1, sim_backend: physx_cuda,"
    )
    evaluation = tiny_evaluation().model_copy(update={"suite_yaml": cuda})
    with pytest.raises(ValueError, match="physx_cuda"):
        make_spec(evaluation=evaluation)
    assert make_spec(evaluation=evaluation, gpu=True).gpu


def test_the_policy_gets_the_gpus_its_suite_asks_for_on_its_own_container():
    manifest = build_job(make_spec(policy_gpus=2, evaluation=gpu_policy_evaluation(2)))
    policy = container(manifest, "policy")["resources"]
    assert policy["requests"][GPU_RESOURCE] == policy["limits"][GPU_RESOURCE] == "2"
    assert GPU_RESOURCE not in container(manifest, "evaluator")["resources"]["limits"]
    assert demand(manifest)[f"requests.{GPU_RESOURCE}"] == 2  # what the quota is asked for


def test_the_policy_gpus_must_be_what_the_suite_asks_for():
    with pytest.raises(ValueError, match="policy_gpus must match"):
        make_spec(policy_gpus=1)  # the tiny suite asks for none
    with pytest.raises(ValueError, match="policy_gpus must match"):
        make_spec(evaluation=gpu_policy_evaluation(1))
    assert make_spec(policy_gpus=1, evaluation=gpu_policy_evaluation(1)).policy_gpus == 1


@pytest.mark.parametrize(
    "gpu_user",
    [
        {"policy_gpus": 1, "evaluation": gpu_policy_evaluation(1)},
        {"gpu": True},  # the evaluator, simulating on physx_cuda: the same pool, the same rule
    ],
    ids=["policy", "evaluator"],
)
def test_a_pod_that_needs_a_gpu_adds_the_gpu_pools_selector_and_tolerations(gpu_user: Json):
    pool = {
        "node_selector": (("manieval.io/pool", "eval"),),
        "tolerations": ((("key", "manieval.io/eval"), ("operator", "Exists")),),
    }
    pod = pod_of(build_job(make_spec(**gpu_user, **pool, **GPU_POOL)))
    assert pod["nodeSelector"] == {
        "manieval.io/pool": "eval",
        "cloud.google.com/gke-accelerator": "nvidia-l4",
    }
    assert pod["tolerations"] == [
        {"key": "manieval.io/eval", "operator": "Exists"},
        {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"},
    ]
    cpu_only = pod_of(build_job(make_spec(**pool, **GPU_POOL)))
    assert cpu_only["nodeSelector"] == {"manieval.io/pool": "eval"}
    assert cpu_only["tolerations"] == [{"key": "manieval.io/eval", "operator": "Exists"}]


def test_no_service_account_token_and_no_service_links():
    pod = pod_of(build_job(make_spec()))
    assert pod["automountServiceAccountToken"] is False
    assert pod["enableServiceLinks"] is False
    assert "serviceAccountName" not in pod


def test_the_policy_container_gets_only_what_the_docker_executor_gives_it():
    manifest = build_job(make_spec())
    policy = container(manifest, "policy")
    assert policy["env"] == [
        {"name": ENDPOINT_ENV, "value": f"unix://{ENDPOINT_DIR}/policy.sock"},
        {"name": "HOME", "value": "/tmp"},
        {"name": "PYTHONUNBUFFERED", "value": "1"},
    ]
    assert "envFrom" not in policy
    assert policy["volumeMounts"] == [
        {"name": "endpoint", "mountPath": "/run/manieval", "readOnly": True},
        {"name": "policy-tmp", "mountPath": "/tmp"},
    ]
    volumes = {v["name"]: v for v in pod_of(manifest)["volumes"]}
    assert volumes["endpoint"]["emptyDir"] == {"medium": "Memory", "sizeLimit": "1Mi"}
    assert all("sizeLimit" in v["emptyDir"] for v in volumes.values() if "emptyDir" in v)
    assert {n for n, v in volumes.items() if "emptyDir" not in v} == {"evaluation"}


def test_the_policy_runs_as_under_the_docker_executor():
    """Same uid, a writable size-limited /tmp, a read-only root: a policy that passes
    `manieval evaluate --image` finds the same on the cluster."""
    limits = ContainerLimits()
    config = container_config(
        image="img@sha256:" + "ab" * 32,
        endpoint="unix:///run/manieval/policy.sock",
        socket_dir=Path("/tmp/sock"),
        name="p",
        labels={},
        limits=limits,
    )
    manifest = build_job(make_spec())
    policy = container(manifest, "policy")
    assert config["user"] == f"{POLICY_UID}:{POLICY_UID}"
    assert policy["securityContext"]["runAsUser"] == POLICY_UID == 65532
    assert policy["securityContext"]["readOnlyRootFilesystem"] is config["read_only"] is True
    assert config["tmpfs"]["/tmp"].startswith(f"size={limits.tmpfs_mib}m")
    volumes = {v["name"]: v for v in pod_of(manifest)["volumes"]}
    assert volumes["policy-tmp"]["emptyDir"] == {
        "medium": "Memory",
        "sizeLimit": f"{limits.tmpfs_mib}Mi",
    }
    env = {e["name"]: e["value"] for e in policy["env"]}
    assert {k: env[k] for k in ("HOME", "PYTHONUNBUFFERED")} == {
        k: config["environment"][k] for k in ("HOME", "PYTHONUNBUFFERED")
    }
    evaluator = container(manifest, "evaluator")
    assert all(m["name"] != "policy-tmp" for m in evaluator["volumeMounts"])


def test_the_policy_is_a_sidecar_the_kubelet_stops_when_the_evaluator_exits():
    pod = pod_of(build_job(make_spec()))
    assert [c["name"] for c in pod["initContainers"]] == ["policy"]
    assert pod["initContainers"][0]["restartPolicy"] == "Always"
    assert [c["name"] for c in pod["containers"]] == ["evaluator"]
    assert pod["restartPolicy"] == "Never"


def test_the_containers_run_as_different_users_of_one_group():
    manifest = build_job(make_spec())
    evaluator = container(manifest, "evaluator")["securityContext"]
    policy = container(manifest, "policy")["securityContext"]
    assert evaluator["runAsUser"] != policy["runAsUser"]
    assert (
        evaluator["runAsGroup"]
        == policy["runAsGroup"]
        == pod_of(manifest)["securityContext"]["runAsGroup"]
    )


def evaluation_read_by(manifest: Json, secret: Json) -> EvaluationJob:
    """What the evaluator reads: the file its env names, in the Secret volume mounted there."""
    evaluator = container(manifest, "evaluator")
    env = {e["name"]: e["value"] for e in evaluator["env"]}
    path = PurePosixPath(env[JOB_SPEC_FILE_ENV])
    (mount,) = [m for m in evaluator["volumeMounts"] if m["mountPath"] == str(path.parent)]
    assert mount["readOnly"] is True
    (volume,) = [v for v in pod_of(manifest)["volumes"] if v["name"] == mount["name"]]
    assert volume["secret"]["secretName"] == secret["metadata"]["name"]
    return EvaluationJob.model_validate_json(secret["stringData"][path.name])


def test_the_evaluator_gets_the_evaluation_its_shard_count_and_the_shared_socket_dir():
    spec = make_spec(shards=2)
    manifest = build_job(spec)
    evaluator = container(manifest, "evaluator")
    env = {e["name"]: e["value"] for e in evaluator["env"]}
    assert evaluation_read_by(manifest, build_secret(spec, job_uid="u")) == spec.evaluation
    assert env[SHARDS_ENV] == "2"
    assert env["MANIEVAL_ENDPOINT_DIR"] == ENDPOINT_DIR
    assert env["MANIEVAL_POLICY"] == spec.policy_image
    assert evaluator["command"] == ["manieval", "evaluate-job"]
    mounts = {m["mountPath"]: m for m in evaluator["volumeMounts"]}
    assert ENDPOINT_DIR.startswith(mounts["/run/manieval"]["mountPath"] + "/")
    assert "readOnly" not in mounts["/run/manieval"]


@pytest.mark.parametrize("version", VERSIONS)
def test_the_evaluation_secret_validates_strictly_and_is_owned_by_the_job(version: str):
    spec = make_spec()
    secret = build_secret(spec, job_uid="5b0e8c55-0000-4000-8000-000000000000")
    assert kubernetes_validate.validate(secret, version, strict=True)
    meta = secret["metadata"]
    assert (meta["name"], meta["namespace"]) == ("eval-7-1-evaluation", spec.namespace)
    assert meta["labels"] == build_job(spec)["metadata"]["labels"]
    assert meta["ownerReferences"] == [
        {
            "apiVersion": "batch/v1",
            "kind": "Job",
            "name": "eval-7-1",
            "uid": "5b0e8c55-0000-4000-8000-000000000000",
            "blockOwnerDeletion": True,  # the Job's foreground deletion waits for it
        }
    ]
    assert secret["immutable"] is True
    assert secret == build_secret(spec, job_uid="5b0e8c55-0000-4000-8000-000000000000")


def test_the_seeds_are_in_no_job_or_pod_object_only_in_the_evaluators_secret_volume():
    evaluation = tiny_evaluation(seeds=(987654321, 123456789))
    spec = make_spec(evaluation=evaluation)
    manifest = build_job(spec)
    text = json.dumps(manifest)
    assert "987654321" not in text
    assert "123456789" not in text
    assert f'"{JOB_SPEC_ENV}"' not in text  # the old way: the whole document in the env
    assert "987654321" in json.dumps(build_secret(spec, job_uid="u"))
    volumes = {v["name"] for v in pod_of(manifest)["volumes"] if "secret" in v}
    assert volumes == {"evaluation"}
    mounted = {
        c["name"]
        for c in containers_of(pod_of(manifest))
        for m in c["volumeMounts"]
        if m["name"] == "evaluation"
    }
    assert mounted == {"evaluator"}  # never the policy


def test_shards_make_an_indexed_job_with_one_pod_per_shard_at_once():
    assert "completionMode" not in build_job(make_spec())["spec"]
    spec = build_job(make_spec(shards=5))["spec"]
    assert (spec["completionMode"], spec["completions"], spec["parallelism"]) == ("Indexed", 5, 5)


def test_disruptions_and_evaluator_errors_each_fail_the_job_without_retries():
    spec = build_job(make_spec())["spec"]
    assert spec["backoffLimit"] == 0
    disrupted, fail = spec["podFailurePolicy"]["rules"]
    assert disrupted == {
        "action": "FailJob",  # the Job itself then says the cluster stopped it
        "onPodConditions": [{"type": "DisruptionTarget", "status": "True"}],
    }
    assert fail["action"] == "FailJob"
    assert fail["onExitCodes"] == {"containerName": "evaluator", "operator": "NotIn", "values": [0]}


def test_deadline_and_ttl_come_from_the_spec():
    plan = tiny_evaluation().plan()
    assert active_deadline_for(plan, startup_s=60) == math.ceil(wall_clock_limit_s(plan)) + 60
    spec = build_job(make_spec())["spec"]
    assert (spec["activeDeadlineSeconds"], spec["ttlSecondsAfterFinished"]) == (900, 600)


def test_the_runtime_class_is_set_on_the_pod_so_it_covers_both_containers():
    assert "runtimeClassName" not in pod_of(build_job(make_spec()))
    pod = pod_of(build_job(make_spec(runtime_class_name="gvisor")))
    assert pod["runtimeClassName"] == "gvisor"


def test_node_pool_settings_are_set_on_the_pod_field_by_field():
    spec = make_spec(**VARIANTS["node-pool"])
    pod = pod_of(build_job(spec))
    assert pod["nodeSelector"] == {"manieval.io/pool": "eval", "kubernetes.io/arch": "amd64"}
    assert pod["tolerations"] == [
        {"key": "manieval.io/eval", "operator": "Exists", "effect": "NoSchedule"},
        {
            "key": "gpu",
            "operator": "Equal",
            "value": "true",
            "effect": "NoExecute",
            "tolerationSeconds": 60,
        },
    ]
    assert pod["priorityClassName"] == "manieval-eval"
    assert pod["imagePullSecrets"] == [{"name": "registry-pull"}, {"name": "mirror-pull"}]
    assert pod["runtimeClassName"] == "gvisor"
    for c in containers_of(pod):  # pod-level only: no container gets any of them
        assert not {"nodeSelector", "tolerations", "imagePullSecrets"} & set(c)


def test_without_node_pool_settings_the_pod_has_none_of_those_fields():
    pod = pod_of(build_job(make_spec()))
    absent = {"nodeSelector", "tolerations", "priorityClassName", "imagePullSecrets"}
    assert not absent & set(pod)


def test_the_worker_settings_become_the_pods_node_pool_fields(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setenv(
        "MANIEVAL_K8S_NODE_SELECTOR", "manieval.io/pool=eval, kubernetes.io/arch=amd64"
    )
    monkeypatch.setenv(
        "MANIEVAL_K8S_TOLERATIONS",
        '[{"key": "manieval.io/eval", "operator": "Exists", "effect": "NoSchedule"}]',
    )
    monkeypatch.setenv("MANIEVAL_K8S_PRIORITY_CLASS", "manieval-eval")
    monkeypatch.setenv("MANIEVAL_K8S_IMAGE_PULL_SECRETS", "registry-pull,mirror-pull")
    monkeypatch.setenv("MANIEVAL_EVALUATOR_IMAGE", "registry.example.org/evaluator:1")
    wsettings = worker_settings(settings)
    assert wsettings.k8s_node_selector == {
        "manieval.io/pool": "eval",
        "kubernetes.io/arch": "amd64",
    }
    assert wsettings.k8s_image_pull_secrets == ("registry-pull", "mirror-pull")
    spec = make_spec()
    handed = Assignment(
        submission_id=7,
        attempt=1,
        plan=spec.evaluation.plan(),
        suite_yaml=spec.evaluation.suite_yaml,
        image=spec.policy_image,
        shards=1,
    )
    pod = pod_of(build_job(job_spec(wsettings, handed)))
    assert pod["nodeSelector"] == {"kubernetes.io/arch": "amd64", "manieval.io/pool": "eval"}
    assert pod["tolerations"] == [
        {"key": "manieval.io/eval", "operator": "Exists", "effect": "NoSchedule"}
    ]
    assert pod["priorityClassName"] == "manieval-eval"
    assert pod["imagePullSecrets"] == [{"name": "registry-pull"}, {"name": "mirror-pull"}]
    monkeypatch.setenv("MANIEVAL_K8S_NODE_SELECTOR", '{"pool": "eval"}')
    assert worker_settings(settings).k8s_node_selector == {"pool": "eval"}
    monkeypatch.setenv("MANIEVAL_K8S_NODE_SELECTOR", "pool")
    with pytest.raises(ValueError, match="key=value"):
        worker_settings(settings)


def test_the_worker_settings_and_the_suite_give_the_policy_a_gpu_on_the_gpu_pool(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setenv(
        "MANIEVAL_K8S_GPU_NODE_SELECTOR", "cloud.google.com/gke-accelerator=nvidia-l4"
    )
    monkeypatch.setenv(
        "MANIEVAL_K8S_GPU_TOLERATIONS",
        '[{"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"}]',
    )
    monkeypatch.setenv("MANIEVAL_POLICY_GPUS", "1")
    monkeypatch.setenv("MANIEVAL_EVALUATOR_IMAGE", "registry.example.org/evaluator:1")
    wsettings = worker_settings(settings)
    assert wsettings.policy_gpus == 1
    evaluation = gpu_policy_evaluation(1)
    handed = Assignment(
        submission_id=7,
        attempt=1,
        plan=evaluation.plan(),
        suite_yaml=evaluation.suite_yaml,
        image=make_spec().policy_image,
        shards=1,
    )
    manifest = build_job(job_spec(wsettings, handed))
    assert container(manifest, "policy")["resources"]["limits"][GPU_RESOURCE] == "1"
    assert pod_of(manifest)["nodeSelector"] == {"cloud.google.com/gke-accelerator": "nvidia-l4"}
    assert pod_of(manifest)["tolerations"] == [
        {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"}
    ]
    monkeypatch.setenv("MANIEVAL_K8S_GPU_NODE_SELECTOR", "accelerator")
    with pytest.raises(ValueError, match="MANIEVAL_K8S_GPU_NODE_SELECTOR is JSON or key=value"):
        worker_settings(settings)


def test_name_and_labels_identify_the_attempt_on_the_job_and_its_pods():
    manifest = build_job(make_spec(submission_id=42, attempt=3))
    labels = {
        "app.kubernetes.io/name": "manieval",
        "manieval.io/submission": "42",
        "manieval.io/attempt": "3",
        "manieval.io/role": "evaluation",
    }
    assert manifest["metadata"] == {
        "name": "eval-42-3",
        "namespace": "manieval-eval",
        "labels": labels,
    }
    assert manifest["spec"]["template"]["metadata"]["labels"] == labels


def test_the_same_spec_always_gives_the_same_manifest():
    first, second = build_job(make_spec(shards=2)), build_job(make_spec(shards=2))
    assert first == second
    assert json.dumps(first) == json.dumps(second)


@pytest.mark.parametrize(
    ("overrides", "problem"),
    [
        ({"policy_image": "127.0.0.1:5000/alice/policy:latest"}, "not pinned"),
        ({"submission_id": 0}, "at least 1"),
        ({"namespace": "Not_A_Label"}, "DNS label"),
        ({"shards": 0}, "shards"),
        ({"shards": 65}, "shards"),
        ({"runtime_class_name": "g Visor"}, "runtime class"),
        ({"node_selector": (("bad key!", "x"),)}, "node selector"),
        ({"node_selector": (("pool", "not a value"),)}, "node selector"),
        ({"tolerations": ((("key", "a"), ("operater", "Exists")),)}, "unknown"),
        ({"tolerations": ((("key", "a"), ("operator", "Matches")),)}, "operator"),
        ({"tolerations": ((("key", "a"), ("effect", "NoRun")),)}, "effect"),
        ({"tolerations": ((("key", "a"), ("operator", "Exists"), ("value", "v")),)}, "Exists"),
        ({"tolerations": ((("key", "a"), ("tolerationSeconds", 5)),)}, "NoExecute"),
        ({"gpu_node_selector": (("gpu pool", "x"),)}, "node selector"),
        ({"gpu_tolerations": ((("key", "a"), ("operator", "Matches")),)}, "operator"),
        ({"priority_class_name": "High Priority"}, "priority class"),
        ({"image_pull_secrets": ("Pull_Secret",)}, "pull secret"),
        ({"evaluator_resources": Resources("-1", "1Gi", "1Gi")}, "quantity"),
        ({"evaluator_resources": Resources("2", "0", "1Gi")}, "quantity"),
        ({"evaluator_resources": Resources("2", "4 GB", "1Gi")}, "quantity"),
    ],
)
def test_an_invalid_spec_is_refused_before_any_manifest_exists(overrides: Json, problem: str):
    with pytest.raises(ValueError, match=problem):
        make_spec(**overrides)


def test_a_payload_too_large_for_one_environment_variable_is_refused():
    many = tuple(range(1_000_000_000, 1_000_000_000 + MAX_PAYLOAD_BYTES // 10))
    with pytest.raises(ValueError, match="exceeds"):
        make_spec(evaluation=tiny_evaluation(seeds=many))


NAMESPACES = st.from_regex(r"\A[a-z0-9]([-a-z0-9]{0,30}[a-z0-9])?\Z")
QUANTITIES = {
    "cpu": st.sampled_from(["100m", "250m", "1", "2", "1.5", "16"]),
    "memory": st.sampled_from(["256Mi", "1Gi", "4Gi", "1G", "64Gi", "2e9"]),
    "ephemeral": st.sampled_from(["100Mi", "1Gi", "20Gi"]),
}
RESOURCES = st.builds(
    Resources,
    cpu=QUANTITIES["cpu"],
    memory=QUANTITIES["memory"],
    ephemeral_storage=QUANTITIES["ephemeral"],
)
IMAGES = st.builds(
    lambda host, path, digest: f"{host}/{path}@sha256:{digest}",
    st.sampled_from(["127.0.0.1:5000", "registry.example.org", "ghcr.io"]),
    st.from_regex(r"\A[a-z0-9]+(/[a-z0-9]+){0,2}\Z"),
    st.from_regex(r"\A[0-9a-f]{64}\Z"),
)
SEEDS = st.lists(st.integers(0, 2**31 - 1), min_size=1, max_size=30)


@st.composite
def specs(draw: st.DrawFn) -> JobSpec:
    return JobSpec(
        submission_id=draw(st.integers(1, 10**12)),
        attempt=draw(st.integers(1, 1000)),
        namespace=draw(NAMESPACES),
        evaluator_image=draw(IMAGES),
        policy_image=draw(IMAGES),
        evaluation=tiny_evaluation(seeds=draw(SEEDS)),
        evaluator_resources=draw(RESOURCES),
        policy_resources=draw(RESOURCES),
        gpu=draw(st.booleans()),
        active_deadline_seconds=draw(st.integers(1, 10**6)),
        ttl_seconds_after_finished=draw(st.integers(0, 10**6)),
        runtime_class_name=draw(st.none() | st.sampled_from(["gvisor", "runsc", "kata-qemu"])),
        shards=draw(st.integers(1, 64)),
        scratch_size=draw(QUANTITIES["ephemeral"]),
        node_selector=draw(
            st.lists(
                st.tuples(
                    st.sampled_from(["pool", "manieval.io/pool", "kubernetes.io/arch"]),
                    st.from_regex(r"\A[a-z0-9]([-a-z0-9]{0,10}[a-z0-9])?\Z"),
                ),
                max_size=3,
                unique_by=lambda pair: pair[0],
            ).map(tuple)
        ),
        tolerations=draw(
            st.lists(
                st.sampled_from(
                    [
                        (
                            ("key", "manieval.io/eval"),
                            ("operator", "Exists"),
                            ("effect", "NoSchedule"),
                        ),
                        (("key", "gpu"), ("operator", "Equal"), ("value", "true")),
                        (("operator", "Exists"),),
                    ]
                ),
                max_size=3,
            ).map(tuple)
        ),
        priority_class_name=draw(st.none() | st.sampled_from(["manieval-eval", "low"])),
        image_pull_secrets=draw(
            st.lists(
                st.sampled_from(["pull", "registry-pull", "a.b"]), max_size=2, unique=True
            ).map(tuple)
        ),
    )


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spec=specs())
def test_any_valid_spec_gives_a_valid_restricted_deterministic_manifest(spec: JobSpec):
    manifest = build_job(spec)
    kubernetes_validate.validate(manifest, "1.30", strict=True)
    assert restricted_violations(pod_of(manifest)) == []
    assert manifest == build_job(spec)
    name = manifest["metadata"]["name"]
    assert re.fullmatch(rf"eval-{spec.submission_id}-{spec.attempt}", name)
    assert len(name) <= 63
    for c in containers_of(pod_of(manifest)):
        assert c["resources"]["requests"] == c["resources"]["limits"]
    secret = build_secret(spec, job_uid="5b0e8c55-0000-4000-8000-000000000000")
    kubernetes_validate.validate(secret, "1.30", strict=True)
    assert evaluation_read_by(manifest, secret) == spec.evaluation
    assert spec.evaluation.canonical_json() not in json.dumps(manifest)
    assert container(manifest, "policy")["env"][0]["name"] == ENDPOINT_ENV
