"""The worker's settings: one object, read from ``MANIEVAL_*`` environment variables.

A worker holds no database URL and no server secret: it reaches the server through
``/internal/v1`` with the worker token, and the broker for wake-ups. Every field is documented
in ``docs/server.md`` (Workers).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
from pathlib import Path
from typing import Annotated, Any, Literal

import platformdirs
from pydantic import Field, SecretStr, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from internal_api.schemas import PINNED_IMAGE


def _default_data_dir() -> Path:
    return Path(platformdirs.user_data_dir("manieval", appauthor=False))


def _default_name() -> str:
    return f"{socket.gethostname()}-{os.getpid()}"


class WorkerSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="MANIEVAL_", extra="ignore", frozen=True)

    server_url: str = "http://127.0.0.1:8000"
    """The ManiEval server the worker reports to (its ``/internal/v1``)."""
    worker_token: SecretStr
    """The bearer token of the internal API (the server's ``MANIEVAL_WORKER_TOKEN``)."""
    worker_name: str = Field(default_factory=_default_name, pattern=r"^[\x21-\x7e]{1,200}$")
    """Recorded with each attempt it claims; a stable name (a StatefulSet pod's, ``embedded``)
    lets a restarted worker end the attempts that died with it at once."""

    broker_url: str = "redis://127.0.0.1:6379/0"
    celery_queue: str = "manieval"
    reconcile_queue: str = "manieval-reconcile"
    """The reconciler's own queue: busy evaluation workers never delay it."""

    data_dir: Path = Field(default_factory=_default_data_dir)
    spool_dir: Path | None = None
    """Final reports not yet accepted by the server (default ``<data_dir>/spool``): kept across
    a restart, sent again while the worker runs and when it starts."""
    report_patience_s: float = Field(default=900.0, gt=0)
    """How long a final report is retried before it is left in the spool."""
    spool_retry_s: float = Field(default=30.0, gt=0)
    """How often a Celery worker tries its spool again while it runs (`worker.spool_sender`):
    a report kept through a network partition lands this soon after the link returns."""
    claim_patience_s: float = Field(default=300.0, gt=0)
    """How long a claim is retried while the server or its database is down."""
    request_timeout_s: float = Field(default=30.0, gt=0)

    allow_local_policies: bool = False
    """Run ``local:NAME`` submissions (the bundled example policies; demo only)."""
    docker_engine_url: str | None = None
    """Docker-API engine that runs policy images (Docker, or Podman's API service, e.g.
    ``unix:///run/manieval/podman.sock``); unset: image submissions end ``error``."""
    evaluation_processes: int = Field(default=0, ge=0, le=64)
    """Evaluator processes per evaluation: its episodes are sharded over this many warm
    processes, started once and kept (docs/capacity.md, "Warm evaluator processes"). 0: in
    the worker's own process (a Celery process that runs one evaluation at a time). The
    embedded worker, whose threads share the server's process, uses at least 1."""
    policy_memory_mib: int = Field(default=2048, ge=64)
    policy_cpus: float = Field(default=1.0, gt=0)
    policy_gpus: int = Field(default=0, ge=0, le=8)
    """GPUs this worker can give one policy container (a suite's ``policy: {gpus: N}``): an
    attempt that asks for more ends ``error`` with the reason; the server's setting of the same
    name refuses such submissions before they are queued. 0: none."""

    executor: Literal["docker", "kubernetes"] = "docker"
    """Where policy images run: ``docker`` (the engine above, evaluator in the worker) or
    ``kubernetes`` (one Job per attempt, evaluator and policy in its pod). Bundled
    ``local:`` policies always run in the worker, when allowed."""
    k8s_namespace: str = "manieval-eval"
    k8s_in_cluster: bool = False
    k8s_kubeconfig: Path | None = None
    k8s_api_url: str | None = None
    evaluator_image: str | None = None
    """The evaluator image of every Job whose challenge names none of its own."""
    evaluator_images: Annotated[tuple[str, ...], NoDecode] = ()
    """Further evaluator images a challenge may name (``manieval challenge load
    --evaluator-image``: one with its task packages), comma or space separated, each pinned by
    digest. A challenge naming another ends its submissions ``error`` (the configuration's)."""
    evaluator_cpu: str = "2"
    evaluator_memory: str = "4Gi"
    k8s_runtime_class: str | None = None
    k8s_runtime_overhead: Annotated[dict[str, str], NoDecode] = Field(default_factory=dict)
    """The RuntimeClass's `overhead.podFixed`, as ``k8s_node_selector`` (``cpu=100m,
    memory=128Mi``): what the quota counts for each pod on top of its containers, so a Job is
    created only when it fits with it."""
    k8s_node_selector: Annotated[dict[str, str], NoDecode] = Field(default_factory=dict)
    """The eval pods' nodeSelector, as JSON (``{"pool": "eval"}``) or ``key=value,...``: keep
    participant code on its own node pool."""
    k8s_tolerations: list[dict[str, str | int]] = Field(default_factory=list)
    """The eval pods' tolerations, as JSON (``[{"key": "manieval.io/eval", "operator":
    "Exists", "effect": "NoSchedule"}]``): for a tainted evaluation node pool."""
    k8s_gpu_node_selector: Annotated[dict[str, str], NoDecode] = Field(default_factory=dict)
    """Added to the nodeSelector of eval pods that request a GPU (the policy's, or the
    evaluator's for a ``physx_cuda`` suite), as ``k8s_node_selector``: the GPU node pool."""
    k8s_gpu_tolerations: list[dict[str, str | int]] = Field(default_factory=list)
    """Added to the tolerations of eval pods that request a GPU, as ``k8s_tolerations`` (the
    GPU pool's taint, often ``nvidia.com/gpu``)."""
    k8s_priority_class: str | None = None
    """The eval pods' PriorityClass (a low one lets the cluster's own pods preempt them)."""
    k8s_image_pull_secrets: Annotated[tuple[str, ...], NoDecode] = ()
    """Secrets in the evaluation namespace for pulling images, comma-separated (or JSON)."""
    k8s_video_claim: str | None = None
    """A ReadWriteMany PersistentVolumeClaim in ``k8s_namespace`` on the storage the server's
    video directory is on: Jobs write episode videos there (docs/videos.md). None: Jobs
    record no videos."""
    k8s_poll_interval: float = Field(default=5.0, gt=0, le=300)
    """Seconds between a watcher's looks at what it knows of its Job (no API request: Jobs and
    pods are watched), and between reads of the quotas while waiting for room."""
    k8s_progress_interval: float = Field(default=120.0, gt=0, le=3600)
    """Seconds between reads of a running evaluation's log for its progress (one API request
    per shard each); the result is read once, at the end."""
    k8s_pending_timeout_s: float = Field(default=600.0, gt=0)
    """How long an evaluation's pods may stay unscheduled, pending, uncreated (a ResourceQuota
    refusing them) or waiting for an image the kubelet retries pulling (its back-off reaches
    300 s) before the attempt ends ``error``: the cluster's fault, but for the participant's
    own policy image."""

    log_format: Literal["text", "json"] = "text"
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"

    @field_validator(
        "k8s_node_selector", "k8s_gpu_node_selector", "k8s_runtime_overhead", mode="before"
    )
    @classmethod
    def _pairs(cls, value: Any, info: ValidationInfo) -> Any:
        if not isinstance(value, str):
            return value
        if value.strip().startswith("{"):
            return json.loads(value)
        pairs = [p.strip() for p in value.split(",") if p.strip()]
        if any("=" not in p for p in pairs):
            raise ValueError(f"MANIEVAL_{str(info.field_name).upper()} is JSON or key=value,...")
        return dict(p.split("=", 1) for p in pairs)

    @field_validator("k8s_image_pull_secrets", mode="before")
    @classmethod
    def _names(cls, value: Any) -> Any:
        if not isinstance(value, str):
            return value
        if value.strip().startswith("["):
            return json.loads(value)
        return tuple(n.strip() for n in value.split(",") if n.strip())

    @field_validator("evaluator_images", mode="before")
    @classmethod
    def _listed(cls, value: Any) -> Any:
        return (
            tuple(i for i in re.split(r"[\s,]+", value) if i) if isinstance(value, str) else value
        )

    @field_validator("evaluator_images")
    @classmethod
    def _pinned(cls, images: tuple[str, ...]) -> tuple[str, ...]:
        for image in images:
            if not PINNED_IMAGE.fullmatch(image):
                raise ValueError(
                    f"MANIEVAL_EVALUATOR_IMAGES: {image} is not pinned by digest "
                    "(REPO@sha256:<64 hex digits>)"
                )
        return images

    @field_validator("server_url")
    @classmethod
    def _url(cls, value: str) -> str:
        if not value.startswith(("http://", "https://")):
            raise ValueError("MANIEVAL_SERVER_URL must start with http:// or https://")
        return value.rstrip("/")

    @field_validator("worker_token")
    @classmethod
    def _token(cls, value: SecretStr) -> SecretStr:
        if len(value.get_secret_value()) < 32:
            raise ValueError("MANIEVAL_WORKER_TOKEN must be at least 32 characters")
        return value

    @property
    def service_id(self) -> str:
        """Which service this worker evaluates for, stable across its restarts and ports and
        shared by all its workers: a fingerprint of the worker token (which it does not reveal)."""
        return hashlib.sha256(self.worker_token.get_secret_value().encode()).hexdigest()[:16]

    @property
    def allowed_evaluator_images(self) -> frozenset[str]:
        """The evaluator images a Job may run: the default and those listed."""
        default = (self.evaluator_image,) if self.evaluator_image else ()
        return frozenset((*default, *self.evaluator_images))

    @property
    def resolved_spool_dir(self) -> Path:
        return self.spool_dir or self.data_dir / "spool"
