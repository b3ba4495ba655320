"""k8s/base/admission.yaml: the API server's own check of what the worker creates.

The policies' CEL expressions run here through cel-python (the Common Expression Language, the
language the API server evaluates them in) against the Job and the Secret a worker of each
overlay creates, which they must admit, and against objects changed one way each, which they
must refuse with the message of the rule broken. No API server runs here; what is checked is
that the rules admit the builder's objects and nothing that strays from them.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable
from typing import Any

import celpy
import pytest

from tests.deploy.manifests import CONTROL_PLANE, EVALUATIONS, OVERLAYS, Json, find, one, render
from tests.deploy.test_operations import core_assignment, worker_settings
from worker.kubernetes.manifest import build_job, build_secret
from worker.kubernetes.spec import job_spec

WORKER = f"system:serviceaccount:{CONTROL_PLANE}:manieval-worker"
JOBS, SECRETS = "manieval-evaluation-jobs", "manieval-evaluation-secrets"
POLICY_IMAGE = "registry.example.org/alice/policy@sha256:" + "ab" * 32
LAB = "registry.example.org/lab/evaluator-lab-tasks@sha256:" + "1a" * 32
OTHER = "registry.example.org/other/evaluator-tasks@sha256:" + "2b" * 32
EVALUATOR_RULE = "its one container is the evaluator, in an evaluator image the workers may run"
_ENV = celpy.Environment()


@functools.cache
def _program(expression: str) -> Any:
    return _ENV.program(_ENV.compile(expression))


def evaluate(expression: str, activation: dict[str, Any]) -> Any:
    return _program(expression).evaluate(activation)


def refusals(policy: Json, obj: Json, params: Json | None, user: str = WORKER) -> list[str]:
    """The messages of the rules `policy` refuses `obj` by; None where it does not apply
    (its match conditions are false). A rule that fails to evaluate refuses, as the API server
    does with `failurePolicy: Fail`."""
    spec = policy["spec"]
    request = {"userInfo": {"username": user}, "operation": "CREATE"}
    activation: dict[str, Any] = {
        "object": celpy.json_to_cel(obj),
        "request": celpy.json_to_cel(request),
        "params": celpy.json_to_cel(params) if params is not None else None,
    }
    for condition in spec.get("matchConditions", []):
        if not evaluate(condition["expression"], activation):
            return ["not matched"]
    variables: dict[str, Any] = {}
    activation["variables"] = variables
    for variable in spec.get("variables", []):
        variables[variable["name"]] = evaluate(variable["expression"], activation)
        activation["variables"] = celpy.celtypes.MapType(
            {celpy.celtypes.StringType(k): v for k, v in variables.items()}
        )
    refused = []
    for rule in spec["validations"]:
        try:
            admitted = evaluate(rule["expression"], activation)
        except celpy.CELEvalError:
            admitted = False
        if not (isinstance(admitted, celpy.celtypes.BoolType) and bool(admitted)):
            refused.append(" ".join(rule["message"].split()))
    return refused


def policies(objects: list[Json]) -> dict[str, Json]:
    return {p["metadata"]["name"]: p for p in find(objects, "ValidatingAdmissionPolicy")}


def params_of(objects: list[Json], overlay_env: dict[str, str] | None = None) -> Json:
    """The worker ConfigMap each binding names as its policy's params (with `overlay_env`
    standing for settings an operator adds to it)."""
    binding = one(objects, "ValidatingAdmissionPolicyBinding", JOBS)
    ref = binding["spec"]["paramRef"]
    (config,) = [
        c
        for c in find(objects, "ConfigMap", ref["name"])
        if c["metadata"]["namespace"] == ref["namespace"]
    ]
    config = copy.deepcopy(config)
    config["data"].update(overlay_env or {})
    return config


def workers_objects(
    overlay: str, monkeypatch: pytest.MonkeyPatch, video_claim: str | None = None
) -> tuple[Json, Json]:
    """The Job and the Secret a worker of `overlay` (given `video_claim`) creates for a
    core-suite evaluation."""
    settings = worker_settings(overlay, monkeypatch)
    if video_claim:
        settings = settings.model_copy(update={"k8s_video_claim": video_claim})
    spec = job_spec(settings, core_assignment())
    return build_job(spec), build_secret(spec, job_uid="5f0c3c1e-1d9b-4f53-9a43-7d2e8c1b1a10")


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_overlay_binds_each_policy_to_the_workers_own_settings(overlay: str):
    objects = render(overlay)
    found = policies(objects)
    assert set(found) == {JOBS, SECRETS}
    for name in found:
        binding = one(objects, "ValidatingAdmissionPolicyBinding", name)
        assert binding["spec"]["policyName"] == name
        assert binding["spec"]["validationActions"] == ["Deny"]
        assert found[name]["spec"]["failurePolicy"] == "Fail"
    assert params_of(objects)["data"]["MANIEVAL_EVALUATOR_IMAGE"]


@pytest.mark.parametrize("video_claim", [None, "manieval-videos"], ids=["no-videos", "videos"])
@pytest.mark.parametrize("overlay", OVERLAYS)
def test_what_a_worker_of_each_overlay_creates_is_admitted(
    overlay: str, video_claim: str | None, monkeypatch: pytest.MonkeyPatch
):
    objects = render(overlay)
    added = {"MANIEVAL_K8S_VIDEO_CLAIM": video_claim} if video_claim else {}
    job, secret = workers_objects(overlay, monkeypatch, video_claim)
    assert (job["metadata"]["namespace"], secret["metadata"]["namespace"]) == (EVALUATIONS,) * 2
    found, params = policies(objects), params_of(objects, added)
    assert refusals(found[JOBS], job, params) == []
    assert refusals(found[SECRETS], secret, None) == []
    if video_claim:
        assert any("persistentVolumeClaim" in v for v in job["spec"]["template"]["spec"]["volumes"])


def _pod(job: Json) -> Json:
    return job["spec"]["template"]["spec"]


def _evaluator(job: Json) -> Json:
    return _pod(job)["containers"][0]


def _policy(job: Json) -> Json:
    return _pod(job)["initContainers"][0]


STRAYS: dict[str, tuple[Callable[[Json], object], str]] = {
    "another-evaluator-image": (
        lambda j: _evaluator(j).update(image="registry.example.org/miner:latest"),
        EVALUATOR_RULE,
    ),
    "a-second-container": (
        lambda j: _pod(j)["containers"].append(dict(_evaluator(j), name="extra")),
        EVALUATOR_RULE,
    ),
    "an-unpinned-policy-image": (
        lambda j: _policy(j).update(image="registry.example.org/alice/policy:latest"),
        "the policy runs beside it, in an image pinned by digest",
    ),
    "a-host-path": (
        lambda j: _pod(j)["volumes"].append({"name": "root", "hostPath": {"path": "/"}}),
        "its volumes are scratch space, its own evaluation Secret and the workers' video claim",
    ),
    "another-jobs-secret": (
        lambda j: _pod(j)["volumes"].append(
            {"name": "other", "secret": {"secretName": "eval-8-1-evaluation"}}
        ),
        "its volumes are scratch space, its own evaluation Secret and the workers' video claim",
    ),
    "a-token-volume": (
        lambda j: _pod(j)["volumes"].append(
            {
                "name": "token",
                "projected": {"sources": [{"serviceAccountToken": {"path": "token"}}]},
            }
        ),
        "its volumes are scratch space, its own evaluation Secret and the workers' video claim",
    ),
    "another-claim": (
        lambda j: _pod(j)["volumes"].append(
            {"name": "data", "persistentVolumeClaim": {"claimName": "postgres-data"}}
        ),
        "its volumes are scratch space, its own evaluation Secret and the workers' video claim",
    ),
    "a-secret-in-the-environment": (
        lambda j: _policy(j)["env"].append(
            {
                "name": "TOKEN",
                "valueFrom": {"secretKeyRef": {"name": "manieval-registry-pull", "key": "x"}},
            }
        ),
        "no container reads a Secret or other object through its environment",
    ),
    "a-secret-as-the-environment": (
        lambda j: _evaluator(j).update(envFrom=[{"secretRef": {"name": "manieval-secrets"}}]),
        "no container reads a Secret or other object through its environment",
    ),
    "privileged": (
        lambda j: _policy(j)["securityContext"].update(privileged=True),
        "no container is privileged, gains privileges or capabilities, or takes a port",
    ),
    "a-capability": (
        lambda j: _policy(j)["securityContext"]["capabilities"].update(add=["NET_RAW"]),
        "no container is privileged, gains privileges or capabilities, or takes a port",
    ),
    "privilege-escalation": (
        lambda j: _evaluator(j)["securityContext"].pop("allowPrivilegeEscalation"),
        "no container is privileged, gains privileges or capabilities, or takes a port",
    ),
    "a-host-port": (
        lambda j: _policy(j).update(ports=[{"containerPort": 80, "hostPort": 80}]),
        "no container is privileged, gains privileges or capabilities, or takes a port",
    ),
    "a-token": (
        lambda j: _pod(j).update(automountServiceAccountToken=True),
        "the pod gets no ServiceAccount token",
    ),
    "the-workers-account": (
        lambda j: _pod(j).update(serviceAccountName="manieval-worker"),
        "the pod gets no ServiceAccount token",
    ),
    "the-nodes-network": (
        lambda j: _pod(j).update(hostNetwork=True),
        "the pod shares none of the node's namespaces",
    ),
    "the-nodes-processes": (
        lambda j: _pod(j).update(hostPID=True),
        "the pod shares none of the node's namespaces",
    ),
    "not-labelled-ours": (
        lambda j: j["metadata"]["labels"].pop("manieval.io/role"),
        "an evaluation Job carries ManiEval's labels",
    ),
}


@pytest.mark.parametrize("stray", list(STRAYS))
def test_a_job_that_strays_from_the_builders_is_refused_by_the_rule_it_breaks(
    stray: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render("production")
    job, _ = workers_objects("production", monkeypatch)
    change, message = STRAYS[stray]
    change(job)
    assert refusals(policies(objects)[JOBS], job, params_of(objects)) == [message]


def test_a_runtime_class_the_workers_set_cannot_be_left_out(monkeypatch: pytest.MonkeyPatch):
    objects = render("gvisor")
    params = params_of(objects)
    assert params["data"]["MANIEVAL_K8S_RUNTIME_CLASS"]
    job, _ = workers_objects("gvisor", monkeypatch)
    assert refusals(policies(objects)[JOBS], job, params) == []
    del _pod(job)["runtimeClassName"]  # the pod would run in runc, outside gVisor
    assert refusals(policies(objects)[JOBS], job, params) == [
        "the pod runs in the workers' RuntimeClass"
    ]


@pytest.mark.parametrize(
    "stray",
    ["another-name", "no-owner", "owner-may-go-first", "a-registry-credential"],
)
def test_a_secret_that_is_not_an_evaluation_jobs_own_is_refused(
    stray: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render("production")
    _, secret = workers_objects("production", monkeypatch)
    owner = secret["metadata"]["ownerReferences"][0]
    if stray == "another-name":
        secret["metadata"]["name"] = "manieval-secrets"
    elif stray == "no-owner":
        del secret["metadata"]["ownerReferences"]
    elif stray == "owner-may-go-first":
        owner["blockOwnerDeletion"] = False
    else:
        secret["type"] = "kubernetes.io/dockerconfigjson"
    assert refusals(policies(objects)[SECRETS], secret, None) != []


def test_the_rules_bind_the_worker_alone(monkeypatch: pytest.MonkeyPatch):
    """Other users (an operator, the Job controller) are RBAC's business, not these rules'."""
    objects = render("production")
    job, _ = workers_objects("production", monkeypatch)
    _pod(job).update(hostNetwork=True)
    operator = "system:serviceaccount:kube-system:deployment-controller"
    assert refusals(policies(objects)[JOBS], job, params_of(objects), user=operator) == [
        "not matched"
    ]


def lab_job(monkeypatch: pytest.MonkeyPatch, image: str = LAB) -> Json:
    """The Job a production worker that lists `image` creates for a challenge naming it."""
    settings = worker_settings("production", monkeypatch)
    settings = settings.model_copy(update={"evaluator_images": (image,)})
    job = build_job(
        job_spec(settings, core_assignment().model_copy(update={"evaluator_image": image}))
    )
    assert _evaluator(job)["image"] == image
    return job


@pytest.mark.parametrize(
    "listed",
    [LAB, f"{OTHER},{LAB}", f"{LAB}, {OTHER}", f"{OTHER}\n{LAB}\n", f"  {OTHER}\t{LAB} "],
    ids=["alone", "last-after-a-comma", "first-before-a-comma", "lines", "blanks"],
)
def test_a_job_on_a_challenges_image_the_workers_list_is_admitted(
    listed: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render("production")
    params = params_of(objects, {"MANIEVAL_EVALUATOR_IMAGES": listed})
    assert refusals(policies(objects)[JOBS], lab_job(monkeypatch), params) == []


@pytest.mark.parametrize(
    ("listed", "image"),
    [
        (None, LAB),
        (OTHER, LAB),
        (f"x{LAB}", LAB),  # an entry that merely ends with it
        (f"{LAB}0", LAB),  # ... or starts with it
        (LAB, LAB.removeprefix("registry.")),  # an image that is part of an entry
        ("", LAB),
    ],
    ids=["no-list", "not-listed", "longer-before", "longer-after", "part-of-an-entry", "empty"],
)
def test_a_job_on_an_image_the_workers_do_not_list_is_refused(
    listed: str | None, image: str, monkeypatch: pytest.MonkeyPatch
):
    objects = render("production")
    params = params_of(objects, {"MANIEVAL_EVALUATOR_IMAGES": listed} if listed is not None else {})
    job = lab_job(monkeypatch, image)
    assert refusals(policies(objects)[JOBS], job, params) == [EVALUATOR_RULE]
