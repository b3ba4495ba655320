"""Publishing the policy base in the embedded registry (docs/registry.md, The policy base).

`manieval serve` and `manieval demo` copy the engine's ``localhost/manieval-base:bookworm``
(what `make install` and docker/policy-base/build.sh make) into the registry they start, as
``manieval/policy-base:bookworm``, with ``skopeo copy`` and a push token the server signs for
itself: the getting-started page then builds participants' images on it, and their pushes
upload only their own layers. Nothing is copied while the registry holds that very image (the
same config digest, which is what the engine calls the image's ID).
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
from collections.abc import Sequence

from server.kit.errors import AppError
from server.kit.settings import Settings
from server.registry.published import LOCAL_POLICY_BASE, POLICY_BASE_REPOSITORY, policy_base
from server.registry.service import publish_token

log = logging.getLogger(__name__)

PUBLISHER_BINARY = "skopeo"
INSTEAD = "participants build it from the template's base/Dockerfile instead"


def copy_args(skopeo: str, *, engine_url: str, target: str, token: str) -> list[str]:
    """`skopeo copy` of the engine's base to `target` (docker://...) on the embedded registry,
    which speaks plain HTTP on the loopback address, with `token` as the bearer token."""
    return [
        *(skopeo, "copy", "--quiet", "--src-daemon-host", engine_url),
        *("--dest-tls-verify=false", "--dest-registry-token", token),
        *(f"docker-daemon:{LOCAL_POLICY_BASE}", target),
    ]


def inspect_args(skopeo: str, *, target: str, token: str) -> list[str]:
    """`skopeo inspect --raw` of the manifest at `target`."""
    return [skopeo, "inspect", "--raw", "--tls-verify=false", "--registry-token", token, target]


def publish_policy_base(settings: Settings, *, domain: str, engine_url: str) -> str | None:
    """Copy the engine's base into the registry at `domain` unless it has it; why it is not
    there, in one line, or None. Bounded by the token's lifetime (skopeo cannot renew it)."""
    skopeo = shutil.which(PUBLISHER_BINARY)
    if skopeo is None:
        return (
            f"the policy base is not published ({PUBLISHER_BINARY} is not installed: "
            f"apt-get install -y {PUBLISHER_BINARY}); {INSTEAD}"
        )
    local = _image_id(engine_url, LOCAL_POLICY_BASE)
    if local is None:
        return (
            f"the policy base is not published: the engine has no {LOCAL_POLICY_BASE} "
            f"(sudo docker/policy-base/build.sh makes it); {INSTEAD}"
        )
    target = f"docker://{policy_base(domain)}"
    try:
        token = publish_token(settings, repository=POLICY_BASE_REPOSITORY)
        if _published_config(inspect_args(skopeo, target=target, token=token)) == local:
            return None
        log.warning("publishing the policy base %s to %s (once)", LOCAL_POLICY_BASE, domain)
        copied = subprocess.run(
            copy_args(skopeo, engine_url=engine_url, target=target, token=token),
            capture_output=True,
            text=True,
            timeout=settings.registry_token_ttl_s,
        )
    except AppError as exc:  # no signing key
        return f"the policy base could not be published to {domain}: {exc.message}; {INSTEAD}"
    except subprocess.TimeoutExpired:
        return (
            f"the policy base could not be published to {domain}: skopeo did not finish within "
            f"{settings.registry_token_ttl_s} s; {INSTEAD}"
        )
    if copied.returncode != 0:
        said = (copied.stderr.strip().splitlines() or ["no message"])[-1]
        return f"the policy base could not be published to {domain}: {said}; {INSTEAD}"
    log.warning("published %s as %s", LOCAL_POLICY_BASE, policy_base(domain))
    return None


def _image_id(engine_url: str, reference: str) -> str | None:
    """The engine's image ID for `reference` (its config's digest), or None without one."""
    from docker.errors import DockerException, ImageNotFound

    from worker.containers import engine

    try:
        client = engine(engine_url)
    except DockerException as exc:
        log.warning("cannot reach the engine at %s: %s", engine_url, exc)
        return None
    try:
        return str(client.images.get(reference).id)
    except ImageNotFound:
        return None
    except DockerException as exc:
        log.warning("cannot ask the engine for %s: %s", reference, exc)
        return None
    finally:
        client.close()


def _published_config(args: Sequence[str]) -> str | None:
    """The config digest of the manifest `skopeo inspect --raw` prints, or None when the
    registry has none there (or does not answer in a minute)."""
    try:
        inspected = subprocess.run(args, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return None
    if inspected.returncode != 0:
        return None
    try:
        return str(json.loads(inspected.stdout)["config"]["digest"])
    except (ValueError, KeyError, TypeError):
        return None
