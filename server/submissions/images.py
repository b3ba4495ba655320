"""Policy images: pin a parsed reference (:mod:`server.kit.image_refs`) to a digest on
an allowed registry. :class:`RegistryClient` asks a registry for the manifest over the OCI
distribution API, checks the digest against the bytes it received and sums the sizes of the
linux/amd64 image, so what is evaluated later is exactly what was checked now.
:func:`image_resolver` turns that into the submit path's resolver, errors as form fields.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from decimal import Decimal
from typing import Any, Protocol

import httpx

from evaluator.bundled import LOCAL_PREFIX, bundled_policies
from server.kit.errors import Invalid, Unavailable
from server.kit.image_refs import (
    DEFAULT_DOMAIN,
    ImageError,
    ImageNotFound,
    ImageReference,
    ImageTooLarge,
    InvalidManifest,
    RegistryNotAllowed,
    RegistryUnavailable,
    ResolvedImage,
    amd64_entry,
    canonical_domain,
    image_size,
    parse_reference,
    verify_digest,
)
from server.kit.settings import Settings
from server.registry.deadline import Deadline, deadline_transport
from server.registry.own import OwnRegistry, own_registry_of
from server.registry.tokens import namespace_for
from server.submissions.service import Resolved

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
_TOKEN_HOSTS = {DEFAULT_DOMAIN: "auth.docker.io"}  # ... and its tokens too
_NOT_FOUND_CODES = frozenset({"MANIFEST_UNKNOWN", "NAME_UNKNOWN"})


class Registry(Protocol):
    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage: ...


class ImageResolver(Protocol):
    """A :data:`Resolver` that also takes the submitting user's name."""

    def __call__(self, image: str, *, owner: str | None = None) -> Resolved: ...


def image_resolver(settings: Settings, registry: Registry | None = None) -> ImageResolver:
    """Validate a submitted reference and pin it through the registry; every problem is a 422
    on the `image` field. With ``owner``, an image on the service's own registry must be in
    that user's namespace."""
    own = own_registry_of(settings)
    client = registry or RegistryClient(
        allowed_registries=settings.allowed_registries,
        insecure_registries=settings.insecure_registries,
        timeout=settings.registry_timeout,
        own_registry=own,
    )

    def resolve(image: str, *, owner: str | None = None) -> Resolved:
        if image.startswith(LOCAL_PREFIX):
            return _resolve_local(image, settings)
        try:
            ref = parse_reference(image)
            if own is not None and owner is not None:
                _check_namespace(ref, own=own, owner=owner)
            resolved = client.resolve(ref, max_bytes=settings.max_image_bytes)
        except RegistryUnavailable as exc:  # ours or theirs, not the participant's: retry later
            raise Unavailable(str(exc), fields={"image": str(exc)}) from None
        except ImageError as exc:
            raise Invalid(str(exc), fields={"image": str(exc)}) from None
        return Resolved(pinned=resolved.pinned, size_bytes=resolved.size_bytes)

    return resolve


def _check_namespace(ref: ImageReference, *, own: OwnRegistry, owner: str) -> None:
    """Participants submit their own images from the service's registry, not each other's."""
    if canonical_domain(ref.domain) != own.domain:
        return
    namespace = namespace_for(owner)
    if namespace is None or ref.path.split("/")[0] != namespace:
        raise ImageNotFound(
            f"images on {ref.domain} must be under your namespace, "
            f"{ref.domain}/{namespace or owner}/..."
        )


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
        own_registry: OwnRegistry | None = None,
    ) -> None:
        if isinstance(allowed_registries, str) or isinstance(insecure_registries, str):
            raise TypeError("registries must be a sequence of domains, not one string")
        self._allowed = frozenset(canonical_domain(d) for d in allowed_registries)
        self._insecure = frozenset(canonical_domain(d) for d in insecure_registries)
        self._timeout = timeout
        self._transport = transport
        self._max_manifest_bytes = max_manifest_bytes
        self._own = own_registry
        self._token_domains = self._allowed | {
            _TOKEN_HOSTS[d] for d in self._allowed if d in _TOKEN_HOSTS
        }
        if own_registry is not None:
            self._allowed |= {own_registry.domain}
            self._token_domains |= {own_registry.domain}

    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage:
        """Pin ``ref`` to its verified manifest digest and measure its linux/amd64 image."""
        domain = canonical_domain(ref.domain)
        own = self._own if self._own is not None and self._own.domain == domain else None
        if domain not in self._allowed and own is None:
            allowed = ", ".join(sorted(self._allowed))
            raise RegistryNotAllowed(
                f"images must come from an allowed registry ({allowed or 'none'}), not {ref.domain}"
            )
        insecure = domain in self._insecure
        base_url = f"{'http' if insecure else 'https'}://{_API_HOSTS.get(domain, ref.domain)}"
        deadline = Deadline(self._timeout)  # one for every hop: manifests, token, index entries
        try:
            with httpx.Client(
                base_url=own.base_url if own is not None else base_url,
                timeout=self._timeout,
                transport=self._transport or deadline_transport(deadline),
            ) as http:
                pull = _Pull(
                    http,
                    ref,
                    deadline=deadline,
                    max_manifest_bytes=self._max_manifest_bytes,
                    allow_http_realm=insecure,
                    token_domains=self._token_domains,
                    token=own.pull_token(ref.path) if own is not None else None,
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
        deadline: Deadline,
        max_manifest_bytes: int,
        allow_http_realm: bool,
        token_domains: frozenset[str],
        token: str | None = None,
    ) -> None:
        self._http = http
        self._ref = ref
        self._deadline = deadline
        self._max_manifest_bytes = max_manifest_bytes
        self._allow_http_realm = allow_http_realm
        self._token_domains = token_domains
        self._token = token

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
        with self._stream(url, headers=self._headers()) as response:
            if response.status_code != 401 or self._token is not None:
                return self._answer(response)
            challenge = response.headers.get("WWW-Authenticate", "")
        self._token = self._fetch_token(challenge)
        with self._stream(url, headers=self._headers()) as response:
            return self._answer(response)

    def _stream(
        self, url: str | httpx.URL, *, headers: dict[str, str] | None = None
    ) -> AbstractContextManager[httpx.Response]:
        """A GET that must be over by the deadline shared by every request of this resolve."""
        return self._http.stream("GET", url, headers=headers, timeout=self._deadline.remaining())

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
        body = bytearray()
        for chunk in response.iter_bytes():
            body += chunk
            if len(body) > limit:
                break
            self._deadline.remaining()  # httpx's timeout is per read, not per body
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
        realm_domain = canonical_domain(f"[{realm.host}]" if ":" in realm.host else realm.host) + (
            f":{realm.port}" if realm.port is not None else ""
        )
        if realm_domain not in self._token_domains:
            raise RegistryNotAllowed(
                f"{ref.domain} sends us for a token to {realm_domain}, which is not an allowed "
                "registry"
            )
        if realm.scheme != "https" and not (realm.scheme == "http" and self._allow_http_realm):
            raise RegistryUnavailable(
                f"{ref.domain} sends us for a token to {realm}, which is not https"
            )
        query = {
            "service": params.get("service", ""),
            "scope": params.get("scope") or f"repository:{ref.path}:pull",
        }
        url = realm.copy_merge_params({key: value for key, value in query.items() if value})
        with self._stream(url) as response:
            body = self._read(response, _MAX_SMALL_BODY)
            if response.status_code != 200:
                raise self._failure(response.status_code, body)
        answer = _json_object(body, what=f"the token from {realm.host}", error=RegistryUnavailable)
        token = answer.get("token") or answer.get("access_token")
        if not isinstance(token, str) or not token:
            raise RegistryUnavailable(f"the token service of {ref.domain} sent no token")
        return token


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
