"""Policy images: parse a submitted reference, then pin it to a digest on an allowed registry.

:func:`parse_reference` follows the grammar and normalisation of the Docker reference library
(github.com/distribution/reference): ``policy`` means ``docker.io/library/policy:latest``.
:class:`RegistryClient` asks a registry for the manifest over the OCI distribution API, checks
the digest against the bytes it received and sums the sizes of the linux/amd64 image, so what is
evaluated later is exactly what was checked now.
"""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any, ClassVar

import httpx

# The grammar, transcribed from distribution/reference regexp.go (ASCII only).
_ALPHANUMERIC = r"[a-z0-9]+"
_SEPARATOR = r"(?:[._]|__|-+)"
_PATH_COMPONENT = rf"{_ALPHANUMERIC}(?:{_SEPARATOR}{_ALPHANUMERIC})*"
_PATH = rf"{_PATH_COMPONENT}(?:/{_PATH_COMPONENT})*"
_DOMAIN_COMPONENT = r"(?:[a-zA-Z0-9]|[a-zA-Z0-9][a-zA-Z0-9-]*[a-zA-Z0-9])"
_DOMAIN_NAME = rf"{_DOMAIN_COMPONENT}(?:\.{_DOMAIN_COMPONENT})*"
_IPV6 = r"\[[a-fA-F0-9:]+\]"
_DOMAIN = rf"(?:{_DOMAIN_NAME}|{_IPV6})(?::[0-9]+)?"
_TAG = r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}"
_DIGEST = r"[A-Za-z][A-Za-z0-9]*(?:[-_+.][A-Za-z][A-Za-z0-9]*)*:[0-9a-fA-F]{32,}"
REFERENCE_PATTERN = rf"(?:{_DOMAIN}/)?{_PATH}(?::{_TAG})?(?:@{_DIGEST})?"

_REFERENCE_RE = re.compile(REFERENCE_PATTERN, re.ASCII)
_DOMAIN_RE = re.compile(_DOMAIN, re.ASCII)
_PATH_COMPONENT_RE = re.compile(_PATH_COMPONENT, re.ASCII)
_TAG_RE = re.compile(_TAG, re.ASCII)
_IDENTIFIER_RE = re.compile(r"[a-f0-9]{64}", re.ASCII)
_DIGEST_HEX_LENGTH = {"sha256": 64, "sha384": 96, "sha512": 128}

DEFAULT_DOMAIN = "docker.io"
NAME_MAX_LENGTH = 255
TAG_MAX_LENGTH = 128
_MAX_REFERENCE_LENGTH = 1024  # longer than any valid reference; keeps the regexes cheap

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


class ImageError(Exception):
    """A submitted image cannot be used; the message is for the participant."""

    status: ClassVar[int] = 422
    code: ClassVar[str] = "invalid_image"


class ImageReferenceError(ImageError, ValueError):
    code = "invalid_image_reference"


class RegistryNotAllowed(ImageError):
    code = "registry_not_allowed"


class ImageNotFound(ImageError):
    code = "image_not_found"


class RegistryUnavailable(ImageError):
    status = 503
    code = "registry_unavailable"


class ImageTooLarge(ImageError):
    code = "image_too_large"


class InvalidManifest(ImageError):
    code = "invalid_manifest"


class UnsupportedPlatform(ImageError):
    code = "unsupported_platform"


@dataclass(frozen=True)
class ImageReference:
    """A parsed, normalised reference; a tag, a digest or both (never neither)."""

    domain: str
    path: str
    tag: str | None
    digest: str | None

    @property
    def name(self) -> str:
        return f"{self.domain}/{self.path}"

    def __str__(self) -> str:
        tag = f":{self.tag}" if self.tag is not None else ""
        digest = f"@{self.digest}" if self.digest is not None else ""
        return f"{self.name}{tag}{digest}"

    def pinned(self, digest: str) -> str:
        """This repository at exactly ``digest``: ``domain/path@sha256:...``."""
        _check_digest(digest, ImageReferenceError)
        return f"{self.name}@{digest}"


@dataclass(frozen=True)
class ResolvedImage:
    """What a reference pointed at when resolved: ``pinned`` is what to run."""

    reference: ImageReference
    digest: str
    size_bytes: int
    pinned: str


def parse_reference(text: str) -> ImageReference:
    """Validate and normalise an image reference such as ``host:5000/team/policy:v3``."""
    _check_characters(text)
    if _IDENTIFIER_RE.fullmatch(text):
        raise ImageReferenceError("a bare 64-digit hex string is an image ID, not a reference")
    rest, at, digest = text.partition("@")
    if at and "@" in digest:
        raise ImageReferenceError("image reference contains more than one '@'")
    name, tag = _split_tag(rest)
    domain, path = _split_domain(name)
    _check_domain(domain)
    _check_path(path)
    if tag is not None:
        _check_tag(tag)
    if at:
        _check_digest(digest, ImageReferenceError)
    if domain == "index.docker.io":
        domain = DEFAULT_DOMAIN
    if domain == DEFAULT_DOMAIN and "/" not in path:
        path = f"library/{path}"
    ref = ImageReference(
        domain, path, tag if tag is not None or at else "latest", digest if at else None
    )
    if len(ref.name) > NAME_MAX_LENGTH:
        raise ImageReferenceError(
            f"repository name is longer than {NAME_MAX_LENGTH} characters "
            f"({len(ref.name)} with the registry)"
        )
    if not _REFERENCE_RE.fullmatch(text):  # the checks above should have said why already
        raise ImageReferenceError("not a valid image reference")
    return ref


def _check_characters(text: str) -> None:
    if not text:
        raise ImageReferenceError("image reference is empty")
    if len(text) > _MAX_REFERENCE_LENGTH:
        raise ImageReferenceError(
            f"image reference is longer than {_MAX_REFERENCE_LENGTH} characters"
        )
    if not text.isascii():
        bad = next(c for c in text if not c.isascii())
        raise ImageReferenceError(f"image reference is not ASCII (it contains {bad!r})")
    if any(c.isspace() for c in text):
        raise ImageReferenceError("image reference contains whitespace")
    if any(not c.isprintable() for c in text):
        raise ImageReferenceError("image reference contains a control character")


def _split_tag(rest: str) -> tuple[str, str | None]:
    name, colon, tag = rest.rpartition(":")
    if not colon or "/" in tag:  # that colon belongs to a registry port
        return rest, None
    return name, tag


def _split_domain(name: str) -> tuple[str, str]:
    """The first component is a registry only if it looks like one (docker's rule)."""
    first, slash, rest = name.partition("/")
    if slash and (first == "localhost" or "." in first or ":" in first or first != first.lower()):
        return first, rest
    return DEFAULT_DOMAIN, name


def _check_domain(domain: str) -> None:
    if not _DOMAIN_RE.fullmatch(domain):
        raise ImageReferenceError(
            f"invalid registry address {domain!r}: expected a host name, IPv4 address or "
            "[IPv6] address, optionally followed by :port"
        )


def _check_path(path: str) -> None:
    if path != path.lower():
        raise ImageReferenceError(f"repository path {path!r} must be lowercase")
    for component in path.split("/"):
        if not component:
            raise ImageReferenceError(f"repository path {path!r} has an empty component")
        bad = re.search(r"[^a-z0-9._-]", component)
        if bad:
            raise ImageReferenceError(
                f"repository path component {component!r} contains {bad.group()!r}; "
                "allowed are a-z, 0-9, '.', '_' and '-'"
            )
        if not (component[0].isalnum() and component[-1].isalnum()):
            raise ImageReferenceError(
                f"repository path component {component!r} must start and end with a letter or digit"
            )
        if not _PATH_COMPONENT_RE.fullmatch(component):
            raise ImageReferenceError(
                f"repository path component {component!r} has an invalid separator; "
                "between letters and digits use one '.', one or two '_', or dashes"
            )


def _check_tag(tag: str) -> None:
    if not tag:
        raise ImageReferenceError("tag is empty")
    bad = re.search(r"[^A-Za-z0-9_.-]", tag)
    if bad:
        raise ImageReferenceError(
            f"tag {tag!r} contains {bad.group()!r}; allowed are letters, digits, '_', '.', '-'"
        )
    if len(tag) > TAG_MAX_LENGTH:
        raise ImageReferenceError(f"tag longer than {TAG_MAX_LENGTH} characters")
    if not _TAG_RE.fullmatch(tag):
        raise ImageReferenceError(f"tag {tag!r} must start with a letter, digit or '_'")


def _check_digest(digest: str, error: type[ImageError]) -> None:
    algorithm, colon, encoded = digest.partition(":")
    if not colon:
        raise error(f"digest {digest!r} must look like sha256:<64 hex digits>")
    length = _DIGEST_HEX_LENGTH.get(algorithm)
    if length is None:
        raise error(f"unsupported digest algorithm {algorithm!r}; use sha256")
    if len(encoded) != length or not re.fullmatch(r"[0-9a-f]+", encoded, re.ASCII):
        raise error(f"{algorithm} digest must be {length} lowercase hex digits")


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
        self._allowed = frozenset(_canonical_domain(d) for d in allowed_registries)
        self._insecure = frozenset(_canonical_domain(d) for d in insecure_registries)
        self._timeout = timeout
        self._transport = transport
        self._max_manifest_bytes = max_manifest_bytes

    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage:
        """Pin ``ref`` to its verified manifest digest and measure its linux/amd64 image."""
        domain = _canonical_domain(ref.domain)
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
    _check_digest(digest, InvalidManifest)
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
        _check_digest(digest, InvalidManifest)
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


def _canonical_domain(domain: str) -> str:
    domain = domain.lower()
    return DEFAULT_DOMAIN if domain == "index.docker.io" else domain


def _megabytes(size: int) -> str:
    """Three significant digits of megabytes (10^6 bytes), never in exponent notation."""
    return f"{Decimal(f'{size / 1_000_000:.3g}'):f} MB"
