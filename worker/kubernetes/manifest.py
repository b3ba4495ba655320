"""Evaluations as Kubernetes Jobs: a pure builder for the manifest and its network policy.

`build_job` turns a JobSpec into the Job manifest, a plain dict, without I/O. The evaluator is
the pod's main container; the participant's pinned image runs as a native sidecar (an init
container with `restartPolicy: Always`, Kubernetes >= 1.29), which the kubelet stops once the
evaluator has exited: a policy that never exits cannot hold the pod, and its exit code never
decides the pod's outcome. Both containers run under the "restricted" Pod Security profile,
with no service-account token and no service links. They share one memory-backed emptyDir that
holds the evaluator's Unix socket; the policy mounts it read-only (connecting to a socket needs
no write access to the mount) and gets nothing else but what the docker executor gives it too:
uid 65532, a 64 MiB memory-backed `/tmp`, and MANIEVAL_ENDPOINT, HOME=/tmp, PYTHONUNBUFFERED.
Kubernetes has no per-pod process limit: the kubelet's `podPidsLimit` on the evaluation node
pool bounds it (docs/deploy.md). The evaluation (its seeds) travels in a per-attempt Secret
(`build_secret`) owned by the Job and mounted into the evaluator alone. Node selector,
tolerations, priority class, runtime class and pull secrets come from the worker's settings. A
container that needs GPUs (the evaluator for a `physx_cuda` suite, the policy when its suite
asks for them) requests them as `nvidia.com/gpu`, and its pod adds the GPU node pool's selector
and tolerations to those of every evaluation pod.
`worker.kubernetes.client` creates, adopts, reads, and deletes those Jobs.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any

from evaluator.endpoint import SOCKET_NAME
from evaluator.job import (
    ENDPOINT_DIR,
    ENDPOINT_DIR_ENV,
    JOB_SPEC_FILE_ENV,
    POLICY_ENV,
    SHARDS_ENV,
    TRAJECTORY_DIR_ENV,
    VIDEO_DIR_ENV,
    EvaluationJob,
)
from evaluator.plan import EvaluationPlan
from evaluator.provenance import EVALUATOR_IMAGE_ENV
from internal_api.schemas import PINNED_IMAGE
from manieval_sdk.serve import ENDPOINT_ENV
from worker.deadline import wall_clock_limit_s

APP_LABEL = "app.kubernetes.io/name"
SUBMISSION_LABEL = "manieval.io/submission"
ATTEMPT_LABEL = "manieval.io/attempt"
ROLE_LABEL = "manieval.io/role"
INDEX_LABEL = "batch.kubernetes.io/job-completion-index"  # set by the Job controller
APP, ROLE = "manieval", "evaluation"
EVALUATOR, POLICY = "evaluator", "policy"
EVALUATOR_UID, SHARED_GID = 10001, 10000
POLICY_UID = 65532
"""The `policy` user of docker/policy-base, as under the docker executor (worker.containers)."""
POLICY_TMP_SIZE = "64Mi"  # the docker executor's /tmp tmpfs (ContainerLimits.tmpfs_mib)
TOLERATION_KEYS = frozenset({"key", "operator", "value", "effect", "tolerationSeconds"})
TOLERATION_OPERATORS = frozenset({"Exists", "Equal"})
TOLERATION_EFFECTS = frozenset({"NoSchedule", "PreferNoSchedule", "NoExecute"})
ENDPOINT_MOUNT = str(PurePosixPath(ENDPOINT_DIR).parent)
SOCKET = f"unix://{ENDPOINT_DIR}/{SOCKET_NAME}"
GPU_RESOURCE = "nvidia.com/gpu"
EVALUATION_KEY = "evaluation.json"
EVALUATION_MOUNT = "/etc/manieval-evaluation"
"""Where the evaluator reads the evaluation (seeds included) from the attempt's Secret."""
VIDEO_MOUNT = "/run/manieval/videos"
"""Where the evaluator writes episode videos: the attempt's directory of the video volume."""
TRAJECTORY_MOUNT_DIR = f"{VIDEO_MOUNT}/trajectories"
"""Where it writes its shard's trajectory parts: the server's layout (`VideoStore`), which
merges every shard's parts when the attempt's final report comes."""
MAX_SHARDS = 64
MAX_PAYLOAD_BYTES = 100_000  # well under a Secret's 1 MiB
_QUANTITY = re.compile(r"^(\d+(\.\d*)?|\.\d+)([KMGTPE]i|[numkMGTPE]|[eE][+-]?\d+)?$")
_DNS_LABEL = re.compile(r"^[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?$")
_DNS_NAME = re.compile(r"^[a-z0-9]([-a-z0-9.]{0,251}[a-z0-9])?$")
_LABEL_KEY = re.compile(
    r"^([a-z0-9]([-a-z0-9.]{0,251}[a-z0-9])?/)?[A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?$"
)
_LABEL_VALUE = re.compile(r"^([A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?)?$")


@dataclass(frozen=True)
class Resources:
    """One container's cpu, memory and ephemeral storage: requested and limited alike."""

    cpu: str
    memory: str
    ephemeral_storage: str

    def as_dict(self) -> dict[str, str]:
        """As Kubernetes names them."""
        return {"cpu": self.cpu, "memory": self.memory, "ephemeral-storage": self.ephemeral_storage}


@dataclass(frozen=True)
class JobSpec:
    """Everything the Job of one attempt of one submission is built from."""

    submission_id: int
    attempt: int
    namespace: str
    evaluator_image: str
    policy_image: str
    evaluation: EvaluationJob
    evaluator_resources: Resources = Resources(cpu="2", memory="4Gi", ephemeral_storage="2Gi")
    policy_resources: Resources = Resources(cpu="1", memory="2Gi", ephemeral_storage="1Gi")
    gpu: bool = False
    """The evaluator gets a GPU: the suite simulates on physx_cuda."""
    policy_gpus: int = 0
    """GPUs for the policy's container (the suite's `policy.gpus`)."""
    active_deadline_seconds: int = 8400
    ttl_seconds_after_finished: int = 3600
    runtime_class_name: str | None = None
    """Pod-level: with gVisor it sandboxes the evaluator as well as the policy."""
    shards: int = 1
    node_selector: tuple[tuple[str, str], ...] = ()
    """The pod's nodeSelector (key, value) pairs: the evaluation node pool."""
    tolerations: tuple[tuple[tuple[str, str | int], ...], ...] = ()
    """The pod's tolerations, each as (field, value) pairs (key, operator, value, effect,
    tolerationSeconds): for tainted evaluation nodes."""
    gpu_node_selector: tuple[tuple[str, str], ...] = ()
    """Added to the nodeSelector of a pod with a container that needs GPUs: the GPU pool."""
    gpu_tolerations: tuple[tuple[tuple[str, str | int], ...], ...] = ()
    """Added to the tolerations of a pod with a container that needs GPUs."""
    priority_class_name: str | None = None
    image_pull_secrets: tuple[str, ...] = ()
    """Secrets in the evaluation namespace to pull the evaluator's and policies' images."""
    scratch_size: str = "1Gi"
    video_claim: str | None = None
    """A ReadWriteMany PersistentVolumeClaim in the evaluation namespace, on the storage the
    server reads videos from: the evaluator (never the policy) writes the attempt's
    trajectories, and videos if `videos`, to its `<submission>/<attempt>` directory. None: the
    Job records neither."""
    videos: bool = False
    """Whether the plan records videos (written only where there is a `video_claim`)."""
    evaluator_command: tuple[str, ...] = ("manieval", "evaluate-job")

    def __post_init__(self) -> None:
        problems = list(self._problems())
        if problems:
            raise ValueError("invalid job spec: " + "; ".join(problems))

    def _problems(self) -> Iterable[str]:
        if self.submission_id < 1 or self.attempt < 1:
            yield "submission_id and attempt must be at least 1"
        if not _DNS_LABEL.match(self.namespace):
            yield f"namespace {self.namespace!r} is not a DNS label"
        if not PINNED_IMAGE.fullmatch(self.policy_image):
            yield f"policy image {self.policy_image!r} is not pinned by digest"
        if not self.evaluator_image or any(c.isspace() for c in self.evaluator_image):
            yield "the evaluator image is empty or has blanks"
        for value in (*_values(self.evaluator_resources, self.policy_resources), self.scratch_size):
            number = _QUANTITY.match(value)
            if number is None or not any(c in "123456789" for c in number.group(1)):
                yield f"{value!r} is not a positive quantity"
        if self.active_deadline_seconds < 1 or self.ttl_seconds_after_finished < 0:
            yield "the deadline must be positive and the TTL not negative"
        if self.video_claim is not None and not _DNS_NAME.match(self.video_claim):
            yield f"video claim {self.video_claim!r} is not a DNS name"
        if self.runtime_class_name is not None and not _DNS_NAME.match(self.runtime_class_name):
            yield f"runtime class {self.runtime_class_name!r} is not a DNS name"
        for key, value in (*self.node_selector, *self.gpu_node_selector):
            if not _LABEL_KEY.match(key) or not _LABEL_VALUE.match(value):
                yield f"node selector {key}={value} is not a label key and value"
        for toleration in (*self.tolerations, *self.gpu_tolerations):
            yield from _toleration_problems(dict(toleration))
        if self.priority_class_name is not None and not _DNS_NAME.match(self.priority_class_name):
            yield f"priority class {self.priority_class_name!r} is not a DNS name"
        for secret in self.image_pull_secrets:
            if not _DNS_NAME.match(secret):
                yield f"image pull secret {secret!r} is not a DNS name"
        if not 1 <= self.shards <= MAX_SHARDS:
            yield f"shards must be within 1..{MAX_SHARDS}"
        if not self.evaluator_command:
            yield "the evaluator command is empty"
        if len(self.evaluation.canonical_json().encode()) > MAX_PAYLOAD_BYTES:
            yield f"the evaluation spec exceeds {MAX_PAYLOAD_BYTES} bytes"
        try:
            plan = self.evaluation.plan()
        except ValueError as exc:
            yield f"the evaluation spec is invalid: {exc}"
        else:
            if needs_gpu(plan) and not self.gpu:
                yield "the suite simulates on physx_cuda: gpu must be set"
            if plan.policy.gpus != self.policy_gpus:
                yield f"the suite gives a policy {plan.policy.gpus} GPUs: policy_gpus must match"

    @property
    def name(self) -> str:
        """The Job's name, the same for every try of this attempt."""
        return job_name(self.submission_id, self.attempt)

    @property
    def on_gpu_nodes(self) -> bool:
        """Whether a container of the pod needs GPUs, so the pod goes to the GPU pool."""
        return self.gpu or self.policy_gpus > 0


def _toleration_problems(toleration: dict[str, str | int]) -> Iterable[str]:
    unknown = set(toleration) - TOLERATION_KEYS
    if unknown:
        yield f"toleration fields {sorted(unknown)} are unknown"
    operator = toleration.get("operator", "Equal")
    if operator not in TOLERATION_OPERATORS:
        yield f"toleration operator {operator!r} is not Exists or Equal"
    key, value = toleration.get("key", ""), toleration.get("value", "")
    if not isinstance(key, str) or (key and not _LABEL_KEY.match(key)):
        yield f"toleration key {key!r} is not a label key"
    if not isinstance(value, str) or (operator == "Exists" and value):
        yield f"toleration value {value!r} must be a string, and empty with Exists"
    effect = toleration.get("effect", "")
    if effect and effect not in TOLERATION_EFFECTS:
        yield f"toleration effect {effect!r} is not one of {sorted(TOLERATION_EFFECTS)}"
    seconds = toleration.get("tolerationSeconds")
    if seconds is not None and (not isinstance(seconds, int) or effect != "NoExecute"):
        yield "tolerationSeconds must be an integer, with effect NoExecute"


def _values(*resources: Resources) -> list[str]:
    return [value for r in resources for value in r.as_dict().values()]


def job_name(submission_id: int, attempt: int) -> str:
    """`eval-<submission>-<attempt>`."""
    return f"eval-{submission_id}-{attempt}"


def secret_name(submission_id: int, attempt: int) -> str:
    """`eval-<submission>-<attempt>-evaluation`: the attempt's evaluation document."""
    return f"{job_name(submission_id, attempt)}-evaluation"


def build_secret(spec: JobSpec, *, job_uid: str) -> dict[str, Any]:
    """The Secret that carries the evaluation (its seeds: secret in the test phase) to the
    evaluator container alone, so they appear in no Job or Pod object. Owned by the Job (uid
    `job_uid`): the garbage collector deletes it with the Job, and nothing else has to; with
    `blockOwnerDeletion`, a foreground deletion of the Job ends only once it is gone, so a Job
    made again under the same name never meets its predecessor's Secret."""
    name = job_name(spec.submission_id, spec.attempt)
    return {
        "apiVersion": "v1",
        "kind": "Secret",
        "metadata": {
            "name": secret_name(spec.submission_id, spec.attempt),
            "namespace": spec.namespace,
            "labels": job_labels(spec.submission_id, spec.attempt),
            "ownerReferences": [
                {
                    "apiVersion": "batch/v1",
                    "kind": "Job",
                    "name": name,
                    "uid": job_uid,
                    "blockOwnerDeletion": True,
                }
            ],
        },
        "type": "Opaque",
        "immutable": True,
        "stringData": {EVALUATION_KEY: spec.evaluation.canonical_json()},
    }


def job_labels(submission_id: int, attempt: int) -> dict[str, str]:
    """The labels on the Job and its pods (the NetworkPolicy selects the pods by them)."""
    return {
        APP_LABEL: APP,
        SUBMISSION_LABEL: str(submission_id),
        ATTEMPT_LABEL: str(attempt),
        ROLE_LABEL: ROLE,
    }


def needs_gpu(plan: EvaluationPlan) -> bool:
    """Whether any task of the plan simulates on the GPU."""
    return any(run.sim_backend == "physx_cuda" for run in plan.runs)


JOB_STARTUP_S = 900
"""Time for the Job's pods to be scheduled (an autoscaler may add a node) and pull both images:
the Job's clock (`startTime`) runs from its first sync by the controller, before all that."""


def active_deadline_for(plan: EvaluationPlan, *, startup_s: int = JOB_STARTUP_S) -> int:
    """The Job's deadline: the whole plan's wall-clock limit, by the rule every executor
    follows (`worker.deadline.wall_clock_limit_s`: the budget and the evaluator's own time),
    plus time to schedule and pull."""
    return math.ceil(wall_clock_limit_s(plan)) + startup_s


def build_job(spec: JobSpec) -> dict[str, Any]:
    """The Job manifest of `spec`: the same spec always gives the same dict."""
    labels = job_labels(spec.submission_id, spec.attempt)
    job_spec: dict[str, Any] = {
        "backoffLimit": 0,
        "activeDeadlineSeconds": spec.active_deadline_seconds,
        "ttlSecondsAfterFinished": spec.ttl_seconds_after_finished,
        "podFailurePolicy": {
            "rules": [
                {
                    # Evicted, preempted, drained: the Job fails and says so itself (reason
                    # PodFailurePolicy, `DISRUPTION_RULE` in status), so a worker that missed
                    # the eviction still charges the cluster. A replacement (Ignore) would run
                    # on the old deadline, the eviction visible nowhere.
                    "action": "FailJob",
                    "onPodConditions": [{"type": "DisruptionTarget", "status": "True"}],
                },
                {
                    "action": "FailJob",  # the evaluator itself broke: ours, never retried
                    "onExitCodes": {"containerName": EVALUATOR, "operator": "NotIn", "values": [0]},
                },
            ]
        },
        "template": {"metadata": {"labels": dict(labels)}, "spec": _pod_spec(spec)},
    }
    if spec.shards > 1:
        job_spec.update(completionMode="Indexed", completions=spec.shards, parallelism=spec.shards)
    return {
        "apiVersion": "batch/v1",
        "kind": "Job",
        "metadata": {"name": spec.name, "namespace": spec.namespace, "labels": labels},
        "spec": job_spec,
    }


def _pod_spec(spec: JobSpec) -> dict[str, Any]:
    pod: dict[str, Any] = {
        "restartPolicy": "Never",
        "automountServiceAccountToken": False,
        "enableServiceLinks": False,
        "terminationGracePeriodSeconds": 2,  # the kubelet's minimum; the evaluator exits on SIGTERM
        "securityContext": {
            "runAsNonRoot": True,
            "runAsGroup": SHARED_GID,
            "seccompProfile": {"type": "RuntimeDefault"},
        },
        "initContainers": [_policy_container(spec)],
        "containers": [_evaluator_container(spec)],
        "volumes": [
            {"name": "endpoint", "emptyDir": {"medium": "Memory", "sizeLimit": "1Mi"}},
            {"name": "scratch", "emptyDir": {"sizeLimit": spec.scratch_size}},
            {"name": "policy-tmp", "emptyDir": {"medium": "Memory", "sizeLimit": POLICY_TMP_SIZE}},
            {
                "name": "evaluation",
                "secret": {
                    "secretName": secret_name(spec.submission_id, spec.attempt),
                    "defaultMode": 0o444,  # the evaluator's uid owns no file of the volume
                    "optional": False,  # the pod waits for the Secret, made after the Job
                },
            },
        ],
    }
    if spec.video_claim is not None:
        claim = {"claimName": spec.video_claim}
        pod["volumes"].append({"name": "videos", "persistentVolumeClaim": claim})
    if spec.runtime_class_name is not None:
        pod["runtimeClassName"] = spec.runtime_class_name
    gpu_pool = spec.on_gpu_nodes
    node_selector = (*spec.node_selector, *(spec.gpu_node_selector if gpu_pool else ()))
    tolerations = (*spec.tolerations, *(spec.gpu_tolerations if gpu_pool else ()))
    if node_selector:
        pod["nodeSelector"] = dict(node_selector)
    if tolerations:
        pod["tolerations"] = [dict(t) for t in tolerations]
    if spec.priority_class_name is not None:
        pod["priorityClassName"] = spec.priority_class_name
    if spec.image_pull_secrets:
        pod["imagePullSecrets"] = [{"name": name} for name in spec.image_pull_secrets]
    return pod


def _evaluator_container(spec: JobSpec) -> dict[str, Any]:
    env = {
        JOB_SPEC_FILE_ENV: f"{EVALUATION_MOUNT}/{EVALUATION_KEY}",
        POLICY_ENV: spec.policy_image,
        SHARDS_ENV: str(spec.shards),
        ENDPOINT_DIR_ENV: ENDPOINT_DIR,
        EVALUATOR_IMAGE_ENV: spec.evaluator_image,  # recorded in the result's provenance
        "HOME": "/tmp",
        "TMPDIR": "/tmp",
    }
    mounts = [
        {"name": "endpoint", "mountPath": ENDPOINT_MOUNT},
        {"name": "scratch", "mountPath": "/tmp"},
        {"name": "evaluation", "mountPath": EVALUATION_MOUNT, "readOnly": True},
    ]
    if spec.video_claim is not None:
        if spec.videos:
            env[VIDEO_DIR_ENV] = VIDEO_MOUNT
        env[TRAJECTORY_DIR_ENV] = TRAJECTORY_MOUNT_DIR
        attempt_dir = f"{spec.submission_id}/{spec.attempt}"  # the server's layout
        mounts.append({"name": "videos", "mountPath": VIDEO_MOUNT, "subPath": attempt_dir})
    return {
        "name": EVALUATOR,
        "image": spec.evaluator_image,
        "imagePullPolicy": "IfNotPresent",
        "command": list(spec.evaluator_command),
        "env": [{"name": k, "value": v} for k, v in env.items()],
        "resources": _resources(spec.evaluator_resources, gpus=1 if spec.gpu else 0),
        "securityContext": _security(EVALUATOR_UID),
        "terminationMessagePolicy": "FallbackToLogsOnError",
        "volumeMounts": mounts,
    }


def _policy_container(spec: JobSpec) -> dict[str, Any]:
    return {
        "name": POLICY,
        "image": spec.policy_image,
        "imagePullPolicy": "IfNotPresent",
        "restartPolicy": "Always",  # a sidecar: stopped by the kubelet when the evaluator ends
        # As under the docker executor (worker.containers.container_config).
        "env": [
            {"name": ENDPOINT_ENV, "value": SOCKET},
            {"name": "HOME", "value": "/tmp"},
            {"name": "PYTHONUNBUFFERED", "value": "1"},
        ],
        "resources": _resources(spec.policy_resources, gpus=spec.policy_gpus),
        "securityContext": _security(POLICY_UID),
        "volumeMounts": [
            {"name": "endpoint", "mountPath": ENDPOINT_MOUNT, "readOnly": True},
            {"name": "policy-tmp", "mountPath": "/tmp"},  # memory-backed, as docker's tmpfs
        ],
    }


def _resources(resources: Resources, *, gpus: int) -> dict[str, dict[str, str]]:
    """Requests = limits, with `gpus` NVIDIA GPUs (the device plugin's resource) if any."""
    wanted = resources.as_dict()
    if gpus:
        wanted[GPU_RESOURCE] = str(gpus)
    return {"requests": wanted, "limits": dict(wanted)}


def _security(uid: int) -> dict[str, Any]:
    return {
        "runAsNonRoot": True,
        "runAsUser": uid,
        "runAsGroup": SHARED_GID,
        "privileged": False,
        "allowPrivilegeEscalation": False,
        "readOnlyRootFilesystem": True,
        "capabilities": {"drop": ["ALL"]},
        "seccompProfile": {"type": "RuntimeDefault"},
    }


def build_network_policy(namespace: str) -> dict[str, Any]:
    """Deny all traffic to and from evaluation pods: the policy shares their network."""
    return {
        "apiVersion": "networking.k8s.io/v1",
        "kind": "NetworkPolicy",
        "metadata": {"name": "manieval-evaluations-isolated", "namespace": namespace},
        "spec": {
            "podSelector": {"matchLabels": {APP_LABEL: APP, ROLE_LABEL: ROLE}},
            "policyTypes": ["Ingress", "Egress"],
        },
    }
