"""k8s/: the service's own registry (k8s/base/registry.yaml, docs/registry.md) as the overlays
render it: a config the real registry starts with and that sends clients for tokens to the
API's public address, the signing key shared with the API (its certificate alone in the
registry), an Ingress for pushes without a body limit, the pull-only credential for evaluation
pods, and a network that lets only the ingress controller and the API reach it."""

from __future__ import annotations

import base64
import json
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import httpx
import jwt
import pytest
import yaml
from cryptography import x509

from server.kit.settings import Settings
from server.registry.config import TOKEN_PATH, registry_config
from server.registry.keys import load_signing_key
from server.registry.tokens import Access, TokenSigner
from tests.deploy.manifests import (
    CONTROL_PLANE,
    EVALUATIONS,
    OVERLAYS,
    REGISTRY_SECRETS,
    REPO,
    Json,
    container,
    find,
    one,
    render,
    secrets_read,
)
from tests.deploy.test_operations import server_settings, worker_settings
from tests.deploy.test_security import INGRESS_CONTROLLER, component, opened, rules
from tests.server.registry_fixture import REGISTRY_BINARY, free_port, require_tool
from worker.kubernetes.manifest import job_labels

PULL_SECRET = "manieval-registry-pull"
SIGNING_SECRET = "manieval-registry-signing"


def registry_pod(objects: list[Json]) -> Json:
    spec: Json = one(objects, "Deployment", "manieval-registry")["spec"]["template"]["spec"]
    return spec


def config_file(objects: list[Json]) -> dict[str, Any]:
    data = one(objects, "ConfigMap", "manieval-registry")["data"]
    config: dict[str, Any] = yaml.safe_load(data["config.yml"])
    return config


def mount(spec: Json, container_name: str, volume: str) -> str:
    c = next(c for c in spec["containers"] if c["name"] == container_name)
    (path,) = [m["mountPath"] for m in c["volumeMounts"] if m["name"] == volume]
    return str(path)


def realm(objects: list[Json]) -> str:
    return str(
        one(objects, "ConfigMap", "manieval-registry-env")["data"]["REGISTRY_AUTH_TOKEN_REALM"]
    )


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_registry_config_is_the_one_the_service_writes(overlay: str) -> None:
    objects = render(overlay)
    spec = registry_pod(objects)
    config = config_file(objects)
    defaults = Settings(dev_mode=True)
    cert = f"{mount(spec, 'registry', 'signing-cert')}/tls.crt"
    expected = registry_config(
        addr=":5000",
        storage=Path(mount(spec, "registry", "storage")),
        realm=config["auth"]["token"]["realm"],
        cert_path=Path(cert),
        service=defaults.registry_service,
        issuer=defaults.registry_issuer,
    )
    assert config["auth"] == expected["auth"]
    assert config["storage"] == expected["storage"]
    assert config["http"] == expected["http"]
    (command,) = [c["command"] for c in spec["containers"]]
    assert command[-1] == f"{mount(spec, 'registry', 'config')}/config.yml"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_real_registry_starts_with_it_and_sends_clients_to_the_apis_token_endpoint(
    overlay: str, tmp_path: Path
) -> None:
    binary = require_tool(REGISTRY_BINARY)
    objects = render(overlay)
    config = config_file(objects)
    # The same file, with the pod's paths and port made this machine's.
    key = tmp_path / "cert"
    key.mkdir()
    dev = one(render("dev"), "Secret", SIGNING_SECRET)["stringData"]
    (key / "tls.crt").write_text(dev["tls.crt"])
    domain = f"127.0.0.1:{free_port()}"
    config["storage"]["filesystem"]["rootdirectory"] = str(tmp_path / "storage")
    config["auth"]["token"]["rootcertbundle"] = str(key / "tls.crt")
    config["http"]["addr"] = domain
    (tmp_path / "config.yml").write_text(yaml.safe_dump(config))
    env = dict(one(objects, "ConfigMap", "manieval-registry-env")["data"])
    with (tmp_path / "log").open("wb") as log:
        process = subprocess.Popen(
            [binary, "serve", str(tmp_path / "config.yml")], env=env, stdout=log, stderr=log
        )
    try:
        challenge = _challenge(process, f"http://{domain}/v2/")
    finally:
        process.terminate()
        process.wait(timeout=10)
    assert challenge == (
        f'Bearer realm="{realm(objects)}",service="{Settings(dev_mode=True).registry_service}"'
    ), (tmp_path / "log").read_text()[-2000:]


def _challenge(process: subprocess.Popen[bytes], url: str) -> str:
    for _ in range(300):
        assert process.poll() is None, "the registry exited"
        try:
            response = httpx.get(url, timeout=2)
        except httpx.TransportError:
            time.sleep(0.05)
            continue
        assert response.status_code == 401
        return response.headers["WWW-Authenticate"]
    raise AssertionError("the registry did not answer")


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_realm_is_the_apis_public_token_endpoint(overlay: str) -> None:
    objects = render(overlay)
    api = one(objects, "Ingress", "manieval")
    host = api["spec"]["rules"][0]["host"]
    scheme = "https" if any(host in t["hosts"] for t in api["spec"].get("tls", [])) else "http"
    assert realm(objects) == f"{scheme}://{host}{TOKEN_PATH}"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_participants_push_through_an_ingress_on_the_registry_domain_without_a_body_limit(
    overlay: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    objects = render(overlay)
    settings = server_settings(overlay, monkeypatch)
    assert settings.registry_domain is not None
    ingress = one(objects, "Ingress", "manieval-registry")
    (rule,) = ingress["spec"]["rules"]
    assert rule["host"] == settings.registry_domain
    (path,) = rule["http"]["paths"]
    assert path["path"] == "/v2/"
    assert path["backend"]["service"] == {"name": "manieval-registry", "port": {"name": "registry"}}
    annotations = ingress["metadata"]["annotations"]
    assert annotations["nginx.ingress.kubernetes.io/proxy-body-size"] == "0"
    assert annotations["nginx.ingress.kubernetes.io/proxy-request-buffering"] == "off"
    if overlay != "dev":
        assert [settings.registry_domain] in [t["hosts"] for t in ingress["spec"]["tls"]]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_api_signs_with_the_mounted_key_and_pins_over_the_service(
    overlay: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    objects = render(overlay)
    settings = server_settings(overlay, monkeypatch)
    api = one(objects, "Deployment", "manieval-api")["spec"]["template"]["spec"]
    assert str(settings.registry_key_dir) == mount(api, "api", "registry-signing")
    (volume,) = [v for v in api["volumes"] if v["name"] == "registry-signing"]
    assert volume["secret"]["secretName"] == SIGNING_SECRET
    assert settings.registry_pull_password is not None
    service = one(objects, "Service", "manieval-registry")
    (port,) = service["spec"]["ports"]
    assert settings.registry_internal_url == (
        f"http://manieval-registry.{CONTROL_PLANE}.svc:{port['port']}"
    )
    registry = container(objects, "Deployment", "manieval-registry", "registry")
    assert {p["name"]: p["containerPort"] for p in registry["ports"]} == {"registry": 5000}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_registry_holds_the_certificate_and_never_the_key(overlay: str) -> None:
    spec = registry_pod(render(overlay))
    assert secrets_read(spec, "registry") == {SIGNING_SECRET}
    (volume,) = [v for v in spec["volumes"] if "secret" in v]
    assert volume["secret"]["items"] == [{"key": "tls.crt", "path": "tls.crt"}]
    assert spec["automountServiceAccountToken"] is False


def test_the_dev_signing_key_signs_tokens_its_certificate_verifies(tmp_path: Path) -> None:
    secret = one(render("dev"), "Secret", SIGNING_SECRET)
    assert secret["type"] == "kubernetes.io/tls"
    for name, text in secret["stringData"].items():
        (tmp_path / name).write_text(text)
    signer = TokenSigner(load_signing_key(tmp_path), service="s", issuer="i", ttl_s=60)
    access = [Access(type="repository", name="alice/p", actions=("pull",))]
    token = signer.issue(subject="alice", access=access).token
    cert = x509.load_pem_x509_certificate((tmp_path / "tls.crt").read_bytes())
    claims = jwt.decode(
        token,
        cert.public_key(),
        algorithms=["ES256"],
        audience="s",
        issuer="i",  # type: ignore[arg-type]
    )
    assert claims["access"] == [{"type": "repository", "name": "alice/p", "actions": ["pull"]}]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_evaluation_pods_pull_with_the_pull_only_credential(
    overlay: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    worker = worker_settings(overlay, monkeypatch)
    assert worker.k8s_image_pull_secrets == (PULL_SECRET,)
    assert REGISTRY_SECRETS[PULL_SECRET][0] == EVALUATIONS


def test_the_dev_pull_secret_holds_the_apis_pull_credential_for_the_registry_domain(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    objects = render("dev")
    settings = server_settings("dev", monkeypatch)
    secrets = {name: o for name in REGISTRY_SECRETS for o in find(objects, "Secret", name)}
    for name, (namespace, kind, keys) in REGISTRY_SECRETS.items():
        assert secrets[name]["metadata"]["namespace"] == namespace
        assert secrets[name]["type"] == kind
        assert set(secrets[name]["stringData"]) == keys
    config = json.loads(secrets[PULL_SECRET]["stringData"][".dockerconfigjson"])
    assert settings.registry_domain is not None
    assert settings.registry_pull_password is not None
    entry = config["auths"][settings.registry_domain]
    password = settings.registry_pull_password.get_secret_value()
    assert (entry["username"], entry["password"]) == (settings.registry_pull_user, password)
    assert base64.b64decode(entry["auth"]).decode() == f"{entry['username']}:{password}"


def test_production_is_told_to_make_the_registrys_secrets() -> None:
    text = (REPO / "docs" / "deploy.md").read_text().replace("\\\n", " ")
    assert re.search(rf"kubectl -n {CONTROL_PLANE} create secret tls {SIGNING_SECRET} ", text)
    pull = re.search(
        rf"kubectl -n {EVALUATIONS} create secret docker-registry {PULL_SECRET} ([^\n]+)", text
    )
    assert pull is not None
    assert "--docker-username=manieval-puller" in pull.group(1)
    assert '--docker-password="$PULL_PASSWORD"' in pull.group(1)
    assert '--from-literal=MANIEVAL_REGISTRY_PULL_PASSWORD="$PULL_PASSWORD"' in text


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_only_the_ingress_controller_and_the_api_reach_the_registry(overlay: str) -> None:
    objects = render(overlay)
    admitted = rules(objects, CONTROL_PLANE, component("registry"), "Ingress")
    assert opened(admitted, "from", *INGRESS_CONTROLLER, CONTROL_PLANE) == {5000}
    assert opened(admitted, "from", component("api"), CONTROL_PLANE, CONTROL_PLANE) == {5000}
    for name in ("worker", "reconciler", "migrate", "postgres", "redis"):
        assert opened(admitted, "from", component(name), CONTROL_PLANE, CONTROL_PLANE) == set()
    evaluation = {**job_labels(41, 2), "batch.kubernetes.io/job-completion-index": "0"}
    assert opened(admitted, "from", evaluation, EVALUATIONS, CONTROL_PLANE) == set()
    api_out = rules(objects, CONTROL_PLANE, component("api"), "Egress")
    assert 5000 in opened(api_out, "to", component("registry"), CONTROL_PLANE, CONTROL_PLANE)
