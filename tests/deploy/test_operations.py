"""k8s/: what keeps an installation running: settings each program reads, one reconciler,
migrations, probes, pinned images, workers that reach the server, and evaluation Jobs that the
namespace admits and the workers can hold."""

from __future__ import annotations

import os
import re
from decimal import Decimal
from pathlib import Path
from urllib.parse import urlsplit

import kubernetes_validate
import pytest
from fastapi.routing import APIRoute

from evaluator.plan import build_plan
from evaluator.suite import SUITES_DIR, load_suite
from internal_api.schemas import Assignment
from server.app import create_app
from server.kit.settings import Settings
from tests.deploy.manifests import (
    CONTROL_PLANE,
    EVALUATIONS,
    OVERLAYS,
    REPO,
    SECRETS,
    Json,
    argv,
    container,
    containers,
    environment,
    find,
    one,
    option,
    pod_templates,
    quantity,
    render,
)
from tests.worker.test_k8s_manifest import restricted_violations
from worker.kubernetes.manifest import active_deadline_for, build_job
from worker.kubernetes.spec import job_spec
from worker.settings import WorkerSettings

PINNED = re.compile(r"^[a-z0-9][^\s@]*@sha256:[0-9a-f]{64}$")
POLICY = f"registry.example.org/alice/policy@sha256:{'ab' * 32}"
AUTOSCALED = [o for o in OVERLAYS if o != "dev"]
# (Deployment, container) of the Celery programs: they read the worker's settings, the API and
# the migration the server's.
WORKERS = [("manieval-worker", "worker"), ("manieval-reconciler", "reconciler")]


def pod_environment(
    overlay: str, kind: str, name: str, container_name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The environment a container of this overlay starts with, as this process's (production's
    Secrets are made by hand: stand-ins of the required length take their place)."""
    objects = render(overlay)
    workload = one(objects, kind, name)
    env = environment(objects, workload, container_name)
    spec = workload["spec"]["template"]["spec"]
    c = next(c for c in containers(spec) if c["name"] == container_name)
    for source in c.get("envFrom", []):
        secret = source.get("secretRef", {}).get("name")
        for key in SECRETS.get(secret, set()) - set(env):
            env[key] = "stand-in-for-a-secret-made-by-hand-" + key.lower()
    for key in [k for k in os.environ if k.startswith("MANIEVAL_")]:
        monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)


def worker_settings(
    overlay: str, monkeypatch: pytest.MonkeyPatch, workload: tuple[str, str] = WORKERS[0]
) -> WorkerSettings:
    """The settings a worker pod (or the reconciler's) of this overlay starts with."""
    pod_environment(overlay, "Deployment", *workload, monkeypatch)
    return WorkerSettings()  # type: ignore[call-arg]


def server_settings(overlay: str, monkeypatch: pytest.MonkeyPatch) -> Settings:
    """The settings an API pod of this overlay starts with."""
    pod_environment(overlay, "Deployment", "manieval-api", "api", monkeypatch)
    return Settings()


def _reads_worker_settings(c: Json) -> bool:
    return argv(c)[:3] == ["celery", "-A", "worker.celery_app"]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_setting_named_is_one_its_program_reads(overlay: str):
    objects = render(overlay)
    server = {f"MANIEVAL_{name.upper()}" for name in Settings.model_fields}
    worker = {f"MANIEVAL_{name.upper()}" for name in WorkerSettings.model_fields}
    programs = set()
    for workload, template in pod_templates(objects):
        for c in containers(template["spec"]):
            if c["image"].startswith("docker.io/library/"):
                continue  # Postgres, Redis
            fields = worker if _reads_worker_settings(c) else server
            programs.add((workload["metadata"]["name"], fields is worker))
            named = {k for k in environment(objects, workload, c["name"]) if "MANIEVAL" in k}
            assert named <= fields, f"{c['name']}: {sorted(named - fields)}"
    expected = {(name, True) for name, _ in WORKERS}
    expected |= {("manieval-api", False), ("manieval-migrate", False)}
    assert programs == expected


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_server_sends_wake_ups_to_the_queue_the_workers_consume(
    overlay: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render(overlay)
    server = server_settings(overlay, monkeypatch)
    assert server.queue == "celery"  # not the embedded default: no worker runs in the API pod
    assert server.rate_limit_backend == "redis"
    worker = worker_settings(overlay, monkeypatch)
    assert worker.celery_queue == server.celery_queue
    consumed = option(argv(container(objects, "Deployment", "manieval-worker", "worker")), "-Q")
    assert consumed == [server.celery_queue]
    reconciler = worker_settings(overlay, monkeypatch, WORKERS[1])
    watched = option(
        argv(container(objects, "Deployment", "manieval-reconciler", "reconciler")), "-Q"
    )
    assert watched == [reconciler.reconcile_queue] != consumed


@pytest.mark.parametrize("workload", WORKERS, ids=[w for w, _ in WORKERS])
@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_workers_settings_are_accepted_and_reach_the_api_and_run_jobs(
    overlay: str, workload: tuple[str, str], monkeypatch: pytest.MonkeyPatch
):
    objects = render(overlay)
    settings = worker_settings(overlay, monkeypatch, workload)
    assert settings.executor == "kubernetes"
    assert settings.k8s_in_cluster is True
    assert settings.k8s_namespace == EVALUATIONS
    assert settings.evaluator_image
    # A stable name, its pod's, so that a restarted worker ends its own attempts at once.
    assert settings.worker_name == f"{workload[0]}-pod"
    # The server's internal API, at the API's Service, on the port that reaches the API pods.
    url = urlsplit(settings.server_url)
    service = one(objects, "Service", "manieval-api")
    name, _, rest = url.hostname.partition(".")  # type: ignore[union-attr]
    assert name == service["metadata"]["name"]
    assert rest in {"", CONTROL_PLANE, f"{CONTROL_PLANE}.svc", f"{CONTROL_PLANE}.svc.cluster.local"}
    (port,) = [p for p in service["spec"]["ports"] if p["port"] == (url.port or 80)]
    api = container(objects, "Deployment", "manieval-api", "api")
    assert port["targetPort"] in {p["name"] for p in api["ports"]}
    assert url.scheme == "http"
    assert url.path == ""
    # Final reports not yet accepted are spooled: on a writable volume (the root is read-only).
    c = container(objects, "Deployment", workload[0], workload[1])
    assert c["securityContext"]["readOnlyRootFilesystem"] is True
    mounts = [Path(m["mountPath"]) for m in c.get("volumeMounts", [])]
    assert any(settings.resolved_spool_dir.is_relative_to(m) for m in mounts)


def test_the_dev_overlay_renders_its_secrets_and_production_none():
    # What each holds: test_security.py.
    assert set(SECRETS) <= {s["metadata"]["name"] for s in find(render("dev"), "Secret")}
    for overlay in AUTOSCALED:
        assert find(render(overlay), "Secret") == [], "production Secrets are made by hand"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_reconciler_runs_exactly_once(overlay: str):
    # It embeds beat, the clock of the reconciling passes: two would run them twice as often.
    objects = render(overlay)
    reconciler = one(objects, "Deployment", "manieval-reconciler")
    assert reconciler["spec"]["replicas"] == 1
    assert reconciler["spec"]["strategy"] == {"type": "Recreate"}
    targets = {o["spec"]["scaleTargetRef"]["name"] for o in find(objects, "ScaledObject")}
    targets |= {
        o["spec"]["scaleTargetRef"]["name"] for o in find(objects, "HorizontalPodAutoscaler")
    }
    assert "manieval-reconciler" not in targets
    words = argv(container(objects, "Deployment", "manieval-reconciler", "reconciler"))
    assert words[:4] == ["celery", "-A", "worker.celery_app", "worker"]
    assert "--beat" in words or "-B" in words
    for workload, template in pod_templates(objects):  # and nothing else runs beat
        for c in containers(template["spec"]):
            if workload["metadata"]["name"] != "manieval-reconciler":
                assert "beat" not in " ".join(argv(c)), workload["metadata"]["name"]
                assert "-B" not in argv(c), workload["metadata"]["name"]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_migration_job_runs_alembic_upgrade_head_with_the_servers_image(overlay: str):
    objects = render(overlay)
    migrate = container(objects, "Job", "manieval-migrate", "migrate")
    assert migrate["command"] == ["alembic", "-c", "/app/alembic.ini", "upgrade", "head"]
    assert migrate["workingDir"] == "/app"
    assert (REPO / "alembic.ini").is_file()  # /app is the repository's root in the image
    api = container(objects, "Deployment", "manieval-api", "api")
    assert migrate["image"] == api["image"]
    # The database URL comes from its own Secret (alembic/env.py reads it alone).
    assert {"secretRef": {"name": "manieval-db"}} in migrate["envFrom"]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_api_is_probed_on_healthz_and_readyz(overlay: str):
    objects = render(overlay)
    api = container(objects, "Deployment", "manieval-api", "api")
    ports = {p["name"]: p["containerPort"] for p in api["ports"]}
    assert ports == {"http": 8000}
    assert api["command"][-4:] == ["--host", "0.0.0.0", "--port", "8000"]
    assert api["livenessProbe"]["httpGet"] == {"path": "/healthz", "port": "http"}
    assert api["startupProbe"]["httpGet"] == {"path": "/healthz", "port": "http"}
    assert api["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "http"}
    service = one(objects, "Service", "manieval-api")
    assert service["spec"]["ports"][0]["targetPort"] == "http"


def test_the_server_answers_on_the_probed_paths(tmp_path):
    settings = Settings(dev_mode=True, data_dir=tmp_path)
    app = create_app(settings, background=False)
    paths = {route.path for route in app.routes if isinstance(route, APIRoute)}
    assert {"/healthz", "/readyz"} <= paths


@pytest.mark.parametrize("overlay", AUTOSCALED)
def test_production_images_are_pinned_by_digest(overlay: str):
    objects = render(overlay)
    for workload, template in pod_templates(objects):
        for c in containers(template["spec"]):
            assert PINNED.match(c["image"]), f"{workload['metadata']['name']}: {c['image']}"
    (config,) = find(objects, "ConfigMap", "manieval-worker-config")
    assert PINNED.match(config["data"]["MANIEVAL_EVALUATOR_IMAGE"])


def test_third_party_images_are_pinned_by_digest_in_every_overlay():
    for overlay in OVERLAYS:
        for _, template in pod_templates(render(overlay)):
            for c in containers(template["spec"]):
                if not c["image"].startswith("manieval-"):
                    assert PINNED.match(c["image"]), c["image"]


def core_assignment() -> Assignment:
    """A full core-suite evaluation, as the server hands it to the worker that claims it."""
    suite = load_suite("maniskill-core")
    plan = build_plan(suite, "dev")
    return Assignment(
        submission_id=1,
        attempt=1,
        image=POLICY,
        plan=plan,
        suite_yaml=(SUITES_DIR / "maniskill-core.yaml").read_text(),
        shards=max(1, min(suite.shards, plan.episode_count())),
    )


def evaluation_job(overlay: str, monkeypatch: pytest.MonkeyPatch) -> Json:
    """The Job a worker of this overlay creates for a full core-suite evaluation."""
    return build_job(job_spec(worker_settings(overlay, monkeypatch), core_assignment()))


def _pod_needs(objects: list[Json], pod: Json) -> dict[str, Decimal]:
    needs: dict[str, Decimal] = {}
    for c in containers(pod):
        for resource, value in c["resources"]["requests"].items():
            needs[resource] = needs.get(resource, Decimal(0)) + quantity(value)
    if "runtimeClassName" in pod:
        runtime = one(objects, "RuntimeClass", pod["runtimeClassName"])
        for resource, value in runtime.get("overhead", {}).get("podFixed", {}).items():
            needs[resource] = needs.get(resource, Decimal(0)) + quantity(value)
    return needs


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_evaluation_job_is_admitted_in_the_evaluation_namespace(
    overlay: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render(overlay)
    job = evaluation_job(overlay, monkeypatch)
    pod = job["spec"]["template"]["spec"]
    assert job["metadata"]["namespace"] == EVALUATIONS
    assert kubernetes_validate.validate(job, "1.30", strict=True)
    assert restricted_violations(pod) == []
    if "runtimeClassName" in pod:
        runtime = one(objects, "RuntimeClass", pod["runtimeClassName"])
        # The worker counts the overhead the quota counts, or it creates Jobs whose pods the
        # quota refuses (and makes them again, and again).
        overhead = worker_settings(overlay, monkeypatch).k8s_runtime_overhead
        assert overhead == runtime.get("overhead", {}).get("podFixed", {})
    (limit_range,) = find(objects, "LimitRange")
    (limits,) = limit_range["spec"]["limits"]
    for c in containers(pod):
        requests, caps = c["resources"]["requests"], c["resources"]["limits"]
        assert requests == caps  # maxLimitRequestRatio 1
        for resource, maximum in limits["max"].items():
            assert quantity(caps[resource]) <= quantity(maximum), f"{c['name']}: {resource}"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_quota_holds_as_many_evaluation_pods_as_it_counts(
    overlay: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render(overlay)
    pod = evaluation_job(overlay, monkeypatch)["spec"]["template"]["spec"]
    hard = one(objects, "ResourceQuota", "evaluations")["spec"]["hard"]
    pods = int(hard["pods"])
    for resource, need in _pod_needs(objects, pod).items():
        for scope in ("requests", "limits"):
            assert pods * need <= quantity(hard[f"{scope}.{resource}"]), f"{scope}.{resource}"


def _concurrency(c: Json) -> int:
    argv = [*c.get("command", []), *c.get("args", [])]
    return int(argv[argv.index("--concurrency") + 1])


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_workers_never_hold_more_evaluations_than_the_quota_admits(overlay: str):
    # A Job over quota gets no pod, yet its deadline runs: the worker slots must not exceed it.
    objects = render(overlay)
    worker = one(objects, "Deployment", "manieval-worker")
    scaled = find(objects, "ScaledObject", "manieval-worker")
    replicas = scaled[0]["spec"]["maxReplicaCount"] if scaled else worker["spec"]["replicas"]
    slots = replicas * _concurrency(container(objects, "Deployment", "manieval-worker", "worker"))
    assert slots <= int(one(objects, "ResourceQuota", "evaluations")["spec"]["hard"]["pods"])


@pytest.mark.parametrize("overlay", AUTOSCALED)
def test_a_worker_scaled_down_may_finish_the_longest_evaluation(overlay: str):
    objects = render(overlay)
    spec = one(objects, "Deployment", "manieval-worker")["spec"]["template"]["spec"]
    core = load_suite("maniskill-core")
    longest = max(
        active_deadline_for(build_plan(core, phase, secret=b"s" * 32, record_video=filmed))
        for phase in core.phases
        for filmed in (False, True)
    )
    assert spec["terminationGracePeriodSeconds"] >= longest
