"""Policy images: pin a parsed reference (:mod:`server.submissions.image_refs`) to a digest on
an allowed registry. :class:`RegistryClient` asks a registry for the manifest over the OCI
distribution API, checks the digest against the bytes it received and sums the sizes of the
linux/amd64 image, so what is evaluated later is exactly what was checked now.
:func:`image_resolver` turns that into the submit path's resolver, errors as form fields.
"""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any, Protocol

import httpx

from evaluator.bundled import LOCAL_PREFIX, bundled_policies
from server.kit.errors import Invalid, Unavailable
from server.kit.settings import Settings
from server.submissions.image_refs import (
    DEFAULT_DOMAIN,
    ImageError,
    ImageNotFound,
    ImageReference,
    ImageTooLarge,
    InvalidManifest,
    RegistryNotAllowed,
    RegistryUnavailable,
    ResolvedImage,
    UnsupportedPlatform,
    canonical_domain,
    check_digest,
    parse_reference,
)
from server.submissions.service import Resolved, Resolver

OCI_INDEX = "application/vnd.oci.image.index.v1+json"
OCI_MANIFEST = "application/vnd.oci.image.manifest.v1+json"
DOCKER_MANIFEST_LIST = "application/vnd.docker.distribution.manifest.list.v2+json"
DOCKER_MANIFEST = "application/vnd.docker.distribution.manifest.v2+json"
_INDEX_TYPES = frozenset({OCI_INDEX, DOCKER_MANIFEST_LIST})
_MANIFEST_TYPES = frozenset({OCI_MANIFEST, DOCKER_MANIFEST})
_ACCEPT = ", ".join((OCI_INDEX, OCI_MANIFEST, DOCKER_MANIFEST_LIST, DOCKER_MANIFEST))
MAX_MANIFEST_BYTES = 4 * 1024 * 1024
_MAX_SMALL_BODY = 64 * 1024  # error bodies and token answers
_API_HOSTS = {DEFAULT_DOMAIN: "registry-1.docker.io"}  # Docker Hub serves its API elsewhere
_NOT_FOUND_CODES = frozenset({"MANIFEST_UNKNOWN", "NAME_UNKNOWN"})


class Registry(Protocol):
    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage: ...


def image_resolver(settings: Settings, registry: Registry | None = None) -> Resolver:
    """Validate a submitted reference and pin it through the registry; every problem is a 422
    on the `image` field."""
    client = registry or RegistryClient(
        allowed_registries=settings.allowed_registries,
        insecure_registries=settings.insecure_registries,
        timeout=settings.registry_timeout,
    )

    def resolve(image: str) -> Resolved:
        if image.startswith(LOCAL_PREFIX):
            return _resolve_local(image, settings)
        try:
            resolved = client.resolve(parse_reference(image), max_bytes=settings.max_image_bytes)
        except RegistryUnavailable as exc:  # ours or theirs, not the participant's: retry later
            raise Unavailable(str(exc), fields={"image": str(exc)}) from None
        except ImageError as exc:
            raise Invalid(str(exc), fields={"image": str(exc)}) from None
        return Resolved(pinned=resolved.pinned, size_bytes=resolved.size_bytes)

    return resolve


def _resolve_local(image: str, settings: Settings) -> Resolved:
    if not settings.allow_local_policies:
        raise Invalid(
            "this server does not accept local policies",
            fields={"image": "submit a container image reference"},
        )
    name = image.removeprefix(LOCAL_PREFIX)
    known = bundled_policies()
    if name not in known:
        raise Invalid(
            f"no bundled policy {name!r}", fields={"image": f"one of: {', '.join(sorted(known))}"}
        )
    return Resolved(pinned=image, size_bytes=None)


class RegistryClient:
    """Pins image references to digests on allowed registries (OCI distribution API)."""

    def __init__(
        self,
        *,
        allowed_registries: Sequence[str],
        insecure_registries: Sequence[str] = (),
        timeout: float = 10.0,
        transport: httpx.BaseTransport | None = None,
        max_manifest_bytes: int = MAX_MANIFEST_BYTES,
    ) -> None:
        if isinstance(allowed_registries, str) or isinstance(insecure_registries, str):
            raise TypeError("registries must be a sequence of domains, not one string")
        self._allowed = frozenset(canonical_domain(d) for d in allowed_registries)
        self._insecure = frozenset(canonical_domain(d) for d in insecure_registries)
        self._timeout = timeout
        self._transport = transport
        self._max_manifest_bytes = max_manifest_bytes

    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage:
        """Pin ``ref`` to its verified manifest digest and measure its linux/amd64 image."""
        domain = canonical_domain(ref.domain)
        if domain not in self._allowed:
            allowed = ", ".join(sorted(self._allowed)) or "none"
            raise RegistryNotAllowed(
                f"images must come from an allowed registry ({allowed}), not {ref.domain}"
            )
        insecure = domain in self._insecure
        host = _API_HOSTS.get(domain, ref.domain)
        try:
            with httpx.Client(
                base_url=f"{'http' if insecure else 'https'}://{host}",
                timeout=self._timeout,
                transport=self._transport,
            ) as http:
                pull = _Pull(
                    http,
                    ref,
                    timeout=self._timeout,
                    max_manifest_bytes=self._max_manifest_bytes,
                    allow_http_realm=insecure,
                )
                digest, size = pull.measure()
        except httpx.TimeoutException as exc:
            raise RegistryUnavailable(
                f"registry {ref.domain} did not answer within {self._timeout:g} s"
            ) from exc
        except (httpx.HTTPError, httpx.InvalidURL) as exc:
            raise RegistryUnavailable(f"cannot reach registry {ref.domain}: {exc}") from exc
        if size > max_bytes:
            raise ImageTooLarge(
                f"{ref} is {_megabytes(size)} (compressed), over the limit of "
                f"{_megabytes(max_bytes)}"
            )
        return ResolvedImage(
            reference=ref, digest=digest, size_bytes=size, pinned=ref.pinned(digest)
        )


@dataclass(frozen=True)
class _Manifest:
    digest: str
    media_type: str
    document: dict[str, Any]


class _Pull:
    """The requests of one resolve, which share one bearer token."""

    def __init__(
        self,
        http: httpx.Client,
        ref: ImageReference,
        *,
        timeout: float,
        max_manifest_bytes: int,
        allow_http_realm: bool,
    ) -> None:
        self._http = http
        self._ref = ref
        self._timeout = timeout
        self._max_manifest_bytes = max_manifest_bytes
        self._allow_http_realm = allow_http_realm
        self._token: str | None = None

    def measure(self) -> tuple[str, int]:
        """The digest to pin, and the size of the image a linux/amd64 machine pulls."""
        ref = self._ref
        top = self._manifest(ref.digest or ref.tag or "latest", expected=ref.digest)
        if top.media_type in _MANIFEST_TYPES:
            return top.digest, image_size(top.document, what=str(ref))
        entry = amd64_entry(top.document, what=str(ref))
        image = self._manifest(entry.digest, expected=entry.digest, expected_size=entry.size)
        if image.media_type not in _MANIFEST_TYPES:
            raise InvalidManifest(
                f"the linux/amd64 entry of {ref} is a {image.media_type}, not an image manifest"
            )
        return top.digest, image_size(image.document, what=f"{ref} (linux/amd64)")

    def _manifest(
        self, reference: str, *, expected: str | None, expected_size: int | None = None
    ) -> _Manifest:
        headers, body = self._get(f"/v2/{self._ref.path}/manifests/{reference}")
        what = f"{self._ref.name}@{expected}" if expected else str(self._ref)
        if expected_size is not None and len(body) != expected_size:
            raise InvalidManifest(
                f"the manifest of {what} is {len(body)} bytes, its index says {expected_size}"
            )
        digest = verify_digest(
            body, claimed=headers.get("Docker-Content-Digest"), expected=expected
        )
        document = _json_object(body, what=f"the manifest of {what}")
        media_type = document.get("mediaType") or headers.get("Content-Type", "").split(";")[0]
        if not isinstance(media_type, str) or media_type not in _INDEX_TYPES | _MANIFEST_TYPES:
            raise InvalidManifest(
                f"the manifest of {what} has unsupported media type {media_type!r}; "
                "push an OCI or Docker v2 image"
            )
        return _Manifest(digest=digest, media_type=media_type, document=document)

    def _get(self, url: str) -> tuple[httpx.Headers, bytes]:
        with self._http.stream("GET", url, headers=self._headers()) as response:
            if response.status_code != 401 or self._token is not None:
                return self._answer(response)
            challenge = response.headers.get("WWW-Authenticate", "")
        self._token = self._fetch_token(challenge)
        with self._http.stream("GET", url, headers=self._headers()) as response:
            return self._answer(response)

    def _headers(self) -> dict[str, str]:
        # identity: a compressed manifest could inflate far past the size cap in one chunk
        headers = {"Accept": _ACCEPT, "Accept-Encoding": "identity"}
        if self._token is not None:
            headers["Authorization"] = f"Bearer {self._token}"
        return headers

    def _answer(self, response: httpx.Response) -> tuple[httpx.Headers, bytes]:
        if response.status_code != 200:
            raise self._failure(response.status_code, self._read(response, _MAX_SMALL_BODY))
        body = self._read(response, self._max_manifest_bytes)
        if len(body) > self._max_manifest_bytes:
            raise InvalidManifest(
                f"the manifest of {self._ref} is larger than {_megabytes(self._max_manifest_bytes)}"
            )
        return response.headers, body

    def _read(self, response: httpx.Response, limit: int) -> bytes:
        """At most ``limit + 1`` bytes of the body, so a caller can tell it was cut."""
        deadline = time.monotonic() + self._timeout
        body = bytearray()
        for chunk in response.iter_bytes():
            body += chunk
            if len(body) > limit:
                break
            if time.monotonic() > deadline:  # httpx's timeout is per read, not per body
                raise RegistryUnavailable(f"registry {self._ref.domain} is sending too slowly")
        return bytes(body[: limit + 1])

    def _failure(self, status: int, body: bytes) -> ImageError:
        ref = self._ref
        codes, messages = _registry_errors(body)
        said = f" (registry said: {'; '.join(messages)})" if messages else ""
        if status == 404 or codes & _NOT_FOUND_CODES:
            return ImageNotFound(f"{ref} was not found on {ref.domain}{said}")
        if status in (401, 403):
            return ImageNotFound(
                f"{ref} does not exist or is not public on {ref.domain}; only public images "
                f"can be evaluated{said}"
            )
        return RegistryUnavailable(f"registry {ref.domain} answered HTTP {status}{said}")

    def _fetch_token(self, challenge: str) -> str:
        """An anonymous pull token, by the Docker registry token protocol."""
        ref = self._ref
        scheme, params = parse_challenge(challenge)
        if scheme != "bearer" or not params.get("realm"):
            raise ImageNotFound(
                f"{ref.domain} wants credentials for {ref.path}; only public images can be "
                "evaluated"
            )
        realm = httpx.URL(params["realm"])
        if realm.scheme != "https" and not (realm.scheme == "http" and self._allow_http_realm):
            raise RegistryUnavailable(
                f"{ref.domain} sends us for a token to {realm}, which is not https"
            )
        query = {
            "service": params.get("service", ""),
            "scope": params.get("scope") or f"repository:{ref.path}:pull",
        }
        url = realm.copy_merge_params({key: value for key, value in query.items() if value})
        with self._http.stream("GET", url) as response:
            body = self._read(response, _MAX_SMALL_BODY)
            if response.status_code != 200:
                raise self._failure(response.status_code, body)
        answer = _json_object(body, what=f"the token from {realm.host}", error=RegistryUnavailable)
        token = answer.get("token") or answer.get("access_token")
        if not isinstance(token, str) or not token:
            raise RegistryUnavailable(f"the token service of {ref.domain} sent no token")
        return token


@dataclass(frozen=True)
class Descriptor:
    media_type: str
    digest: str
    size: int


def descriptor(raw: object, *, what: str) -> Descriptor:
    """A content descriptor (mediaType, digest, size) of a manifest, checked."""
    if not isinstance(raw, dict):
        raise InvalidManifest(f"{what}: a descriptor is not a JSON object")
    digest, size, media_type = raw.get("digest"), raw.get("size"), raw.get("mediaType", "")
    if not isinstance(digest, str):
        raise InvalidManifest(f"{what}: a descriptor has no digest")
    check_digest(digest, InvalidManifest)
    if not isinstance(size, int) or isinstance(size, bool) or size < 0:
        raise InvalidManifest(f"{what}: descriptor {digest} has no valid size")
    return Descriptor(media_type=str(media_type), digest=digest, size=size)


def image_size(manifest: Mapping[str, Any], *, what: str) -> int:
    """Bytes a pull downloads: the config blob plus every layer, as the manifest states."""
    layers = manifest.get("layers")
    if not isinstance(layers, list):
        raise InvalidManifest(f"the manifest of {what} has no layer list")
    config = descriptor(manifest.get("config"), what=f"config of {what}")
    return config.size + sum(descriptor(layer, what=f"layer of {what}").size for layer in layers)


def amd64_entry(index: Mapping[str, Any], *, what: str) -> Descriptor:
    """The linux/amd64 entry of an OCI image index or Docker manifest list."""
    entries = index.get("manifests")
    if not isinstance(entries, list):
        raise InvalidManifest(f"the image index of {what} has no manifest list")
    platforms = []
    for raw in entries:
        platform = raw.get("platform") if isinstance(raw, dict) else None
        if not isinstance(platform, dict):
            continue
        if platform.get("os") == "linux" and platform.get("architecture") == "amd64":
            return descriptor(raw, what=f"the image index of {what}")
        platforms.append(f"{platform.get('os')}/{platform.get('architecture')}")
    found = ", ".join(sorted(set(platforms))) or "none"
    raise UnsupportedPlatform(
        f"{what} has no linux/amd64 image (it has: {found}); build it for linux/amd64"
    )


def verify_digest(body: bytes, *, claimed: str | None, expected: str | None) -> str:
    """The digest of ``body``, once it matches what we asked for and what the registry says."""
    for digest in (expected, claimed):
        if digest is None:
            continue
        check_digest(digest, InvalidManifest)
        algorithm = digest.partition(":")[0]
        actual = f"{algorithm}:{hashlib.new(algorithm, body).hexdigest()}"
        if actual != digest:
            raise InvalidManifest(
                f"manifest content does not match its digest: expected {digest}, "
                f"the bytes received hash to {actual}"
            )
    return expected or f"sha256:{hashlib.sha256(body).hexdigest()}"


def parse_challenge(header: str) -> tuple[str, dict[str, str]]:
    """``Bearer realm="...",service="..."`` as ``("bearer", {"realm": ..., ...})``."""
    scheme, _, rest = header.strip().partition(" ")
    pairs = re.findall(r'(\w+)\s*=\s*(?:"([^"]*)"|([^\s,"]*))', rest)
    return scheme.lower(), {key.lower(): quoted or bare for key, quoted, bare in pairs}


def _registry_errors(body: bytes) -> tuple[frozenset[str], list[str]]:
    """The codes and messages of a distribution API error body, if it is one."""
    try:
        errors = json.loads(body)["errors"]
        codes = frozenset(str(error["code"]) for error in errors)
        messages = [str(error.get("message", ""))[:200] for error in errors]
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
        return frozenset(), []
    return codes, [message for message in messages if message][:3]


def _json_object(
    body: bytes, *, what: str, error: type[ImageError] = InvalidManifest
) -> dict[str, Any]:
    try:
        document = json.loads(body)
    except (ValueError, RecursionError) as exc:
        raise error(f"{what} is not valid JSON") from exc
    if not isinstance(document, dict):
        raise error(f"{what} is not a JSON object")
    return document


def _megabytes(size: int) -> str:
    """Three significant digits of megabytes (10^6 bytes), never in exponent notation."""
    return f"{Decimal(f'{size / 1_000_000:.3g}'):f} MB"
