"""k8s/: what keeps an installation running: settings the server reads, one beat, migrations,
probes, pinned images, and evaluation Jobs that the namespace admits and the workers can hold."""

from __future__ import annotations

import os
import re
from decimal import Decimal

import kubernetes_validate
import pytest
from fastapi.routing import APIRoute

from evaluator.plan import build_plan
from evaluator.suite import SUITES_DIR, load_suite
from server.app import create_app
from server.kit.settings import Settings
from tests.deploy.manifests import (
    EVALUATIONS,
    OVERLAYS,
    REPO,
    Json,
    container,
    containers,
    environment,
    find,
    one,
    pod_templates,
    quantity,
    render,
)
from tests.worker.test_k8s_manifest import restricted_violations
from worker.kubernetes.manifest import active_deadline_for, build_job
from worker.kubernetes.watch import job_spec

PINNED = re.compile(r"^[a-z0-9][^\s@]*@sha256:[0-9a-f]{64}$")
SECRET_KEYS = {
    "MANIEVAL_SECRET_KEY",
    "MANIEVAL_SEED_SECRET",
    "MANIEVAL_WORKER_TOKEN",
    "MANIEVAL_DATABASE_URL",
    "MANIEVAL_BROKER_URL",
    "MANIEVAL_REDIS_URL",
}
POLICY = f"registry.example.org/alice/policy@sha256:{'ab' * 32}"
AUTOSCALED = [o for o in OVERLAYS if o != "dev"]


def worker_settings(overlay: str, monkeypatch: pytest.MonkeyPatch) -> Settings:
    """The settings a worker pod of this overlay starts with (production's Secret is made by
    hand: stand-ins of the required length take its place)."""
    objects = render(overlay)
    env = environment(objects, one(objects, "Deployment", "manieval-worker"), "worker")
    for key in SECRET_KEYS - set(env):
        env[key] = "stand-in-for-a-secret-made-by-hand-" + key.lower()
    for key in [k for k in os.environ if k.startswith("MANIEVAL_")]:
        monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return Settings()


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_setting_named_is_one_the_server_reads(overlay: str):
    objects = render(overlay)
    fields = {f"MANIEVAL_{name.upper()}" for name in Settings.model_fields}
    for workload, template in pod_templates(objects):
        for c in containers(template["spec"]):
            if c["image"].startswith("docker.io/library/"):
                continue  # Postgres, Redis
            named = {k for k in environment(objects, workload, c["name"]) if "MANIEVAL" in k}
            assert named <= fields, f"{c['name']}: {sorted(named - fields)}"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_workers_settings_are_accepted_and_run_evaluations_as_jobs(
    overlay: str, monkeypatch: pytest.MonkeyPatch
):
    settings = worker_settings(overlay, monkeypatch)
    assert settings.queue == "celery"
    assert settings.executor == "kubernetes"
    assert settings.k8s_in_cluster is True
    assert settings.k8s_namespace == EVALUATIONS
    assert settings.rate_limit_backend == "redis"
    assert settings.evaluator_image


def test_the_dev_secret_holds_every_secret_setting_and_production_none():
    (secret,) = find(render("dev"), "Secret", "manieval-secrets")
    assert set(secret["stringData"]) == SECRET_KEYS
    for overlay in AUTOSCALED:
        assert find(render(overlay), "Secret") == [], "production Secrets are made by hand"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_beat_runs_exactly_once(overlay: str):
    objects = render(overlay)
    beat = one(objects, "Deployment", "manieval-beat")
    assert beat["spec"]["replicas"] == 1
    assert beat["spec"]["strategy"] == {"type": "Recreate"}
    targets = {o["spec"]["scaleTargetRef"]["name"] for o in find(objects, "ScaledObject")}
    targets |= {
        o["spec"]["scaleTargetRef"]["name"] for o in find(objects, "HorizontalPodAutoscaler")
    }
    assert "manieval-beat" not in targets
    argv = container(objects, "Deployment", "manieval-beat", "beat")
    assert argv["command"] == ["celery", "-A", "worker.celery_app", "beat"]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_migration_job_runs_alembic_upgrade_head_with_the_servers_image(overlay: str):
    objects = render(overlay)
    migrate = container(objects, "Job", "manieval-migrate", "migrate")
    assert migrate["command"] == ["alembic", "-c", "/app/alembic.ini", "upgrade", "head"]
    assert migrate["workingDir"] == "/app"
    assert (REPO / "alembic.ini").is_file()  # /app is the repository's root in the image
    api = container(objects, "Deployment", "manieval-api", "api")
    assert migrate["image"] == api["image"]
    # The database URL (and the secrets the settings insist on) come from the Secret.
    assert {"secretRef": {"name": "manieval-secrets"}} in migrate["envFrom"]


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
    (config,) = find(objects, "ConfigMap", "manieval-config")
    assert PINNED.match(config["data"]["MANIEVAL_EVALUATOR_IMAGE"])


def test_third_party_images_are_pinned_by_digest_in_every_overlay():
    for overlay in OVERLAYS:
        for _, template in pod_templates(render(overlay)):
            for c in containers(template["spec"]):
                if not c["image"].startswith("manieval-"):
                    assert PINNED.match(c["image"]), c["image"]


def evaluation_job(overlay: str, monkeypatch: pytest.MonkeyPatch) -> Json:
    """The Job a worker of this overlay creates for a full core-suite evaluation."""
    settings = worker_settings(overlay, monkeypatch)
    suite = load_suite("maniskill-core")
    plan = build_plan(suite, "dev")
    suite_yaml = (SUITES_DIR / "maniskill-core.yaml").read_text()
    spec = job_spec(settings, 1, 1, plan, suite=suite, suite_yaml=suite_yaml, pinned=POLICY)
    return build_job(spec)


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
        one(objects, "RuntimeClass", pod["runtimeClassName"])
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
    longest = active_deadline_for(load_suite("maniskill-core").limits)
    assert spec["terminationGracePeriodSeconds"] >= longest
