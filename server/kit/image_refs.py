"""Image references: the grammar and normalisation of the Docker reference library.

:func:`parse_reference` follows github.com/distribution/reference: ``policy`` means
``docker.io/library/policy:latest``. The errors of the whole image path (parsing here, resolving
in :mod:`server.submissions.images`) share one base class, :class:`ImageError`. The checks of
what a reference points at (descriptors, manifests, digests) are pure functions here too.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from internal_api.schemas import PINNED_IMAGE

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
        check_digest(digest, ImageReferenceError)
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
        check_digest(digest, ImageReferenceError)
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


def pinned_reference(text: str) -> str:
    """``text`` if it names exactly one image, by digest (``domain/path@sha256:<hex>``, the
    rule workers run images by: `internal_api.schemas.PINNED_IMAGE`); ImageReferenceError
    saying why not."""
    ref = parse_reference(text)  # a malformed reference: what is wrong with it
    if ref.digest is None:
        raise ImageReferenceError(
            f"{text} names a tag, which can move: pin it by digest "
            f"({ref.name}@sha256:<digest>, the digest the registry gave the push)"
        )
    if not PINNED_IMAGE.fullmatch(text):
        raise ImageReferenceError(f"{text} is not pinned by a sha256 digest")
    return text


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


def check_digest(digest: str, error: type[ImageError]) -> None:
    algorithm, colon, encoded = digest.partition(":")
    if not colon:
        raise error(f"digest {digest!r} must look like sha256:<64 hex digits>")
    length = _DIGEST_HEX_LENGTH.get(algorithm)
    if length is None:
        raise error(f"unsupported digest algorithm {algorithm!r}; use sha256")
    if len(encoded) != length or not re.fullmatch(r"[0-9a-f]+", encoded, re.ASCII):
        raise error(f"{algorithm} digest must be {length} lowercase hex digits")


def canonical_domain(domain: str) -> str:
    domain = domain.lower()
    return DEFAULT_DOMAIN if domain == "index.docker.io" else domain


# What a reference points at: content descriptors and manifests, checked ---------------------


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
