"""The reference grammar (server.kit.image_refs) and resolving against a real registry
(server.submissions.images).

The grammar tests compare parse_reference with an independent transcription of
distribution/reference's regexp.go. The registry tests push images over the distribution HTTP
API to Debian's docker-registry and check what resolve pins; only tampered or malformed answers,
which a real registry will not give, come from an httpx.MockTransport.
"""

from __future__ import annotations

import hashlib
import json
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.kit.image_refs import (
    ImageError,
    ImageNotFound,
    ImageReference,
    ImageReferenceError,
    ImageTooLarge,
    InvalidManifest,
    RegistryNotAllowed,
    RegistryUnavailable,
    ResolvedImage,
    UnsupportedPlatform,
    amd64_entry,
    image_size,
    parse_reference,
    verify_digest,
)
from server.submissions.images import (
    DOCKER_MANIFEST,
    DOCKER_MANIFEST_LIST,
    OCI_INDEX,
    OCI_MANIFEST,
    RegistryClient,
    parse_challenge,
)
from tests.server.registry_fixture import (  # noqa: F401 - fixture_*: pytest fixtures
    LocalRegistry,
    PushedImage,
    fixture_registry,
    fixture_token_registry,
    free_port,
    push_image,
    push_index,
    sha256_digest,
)

HEX = "0123456789abcdef" * 4
SHA256 = f"sha256:{HEX}"
MB = 1_000_000

# regexp.go of distribution/reference, written out again here as the oracle.
_ORACLE_DOMAIN = (
    r"(?:(?:[a-zA-Z0-9]|[a-zA-Z0-9][a-zA-Z0-9-]*[a-zA-Z0-9])"
    r"(?:\.(?:[a-zA-Z0-9]|[a-zA-Z0-9][a-zA-Z0-9-]*[a-zA-Z0-9]))*|\[[a-fA-F0-9:]+\])(?::[0-9]+)?"
)
_ORACLE_COMPONENT = r"[a-z0-9]+(?:(?:[._]|__|[-]+)[a-z0-9]+)*"
ORACLE = (
    rf"(?:{_ORACLE_DOMAIN}/)?{_ORACLE_COMPONENT}(?:/{_ORACLE_COMPONENT})*"
    r"(?::[a-zA-Z0-9_][a-zA-Z0-9_.-]{0,127})?"
    r"(?:@[A-Za-z][A-Za-z0-9]*(?:[-_+.][A-Za-z][A-Za-z0-9]*)*:[0-9a-fA-F]{32,})?"
)
# What the library refuses although the grammar matches: unknown digests, long names, bare
# image IDs, and a first component that docker takes for a registry but is not a valid one.
EXTRA_RULES = ("digest", "longer than", "image ID", "invalid registry address")


# The grammar ----------------------------------------------------------------------------------

VALID = [
    ("ubuntu", "docker.io/library/ubuntu:latest"),
    ("ubuntu:22.04", "docker.io/library/ubuntu:22.04"),
    ("team/policy", "docker.io/team/policy:latest"),
    ("docker.io/ubuntu", "docker.io/library/ubuntu:latest"),
    ("index.docker.io/team/policy:v1", "docker.io/team/policy:v1"),
    ("registry.example.org:5000/team/policy:v3", "registry.example.org:5000/team/policy:v3"),
    ("registry.example.org/a/b/c/d:x", "registry.example.org/a/b/c/d:x"),
    ("localhost/policy", "localhost/policy:latest"),
    ("localhost:5000/policy:1", "localhost:5000/policy:1"),
    ("127.0.0.1:5000/team/policy", "127.0.0.1:5000/team/policy:latest"),
    ("[::1]:5000/policy:v1", "[::1]:5000/policy:v1"),
    ("[2001:db8::1]/team/policy", "[2001:db8::1]/team/policy:latest"),
    ("Registry.Example.ORG/policy", "Registry.Example.ORG/policy:latest"),
    ("Myhost/policy", "Myhost/policy:latest"),  # an uppercase first component is a domain
    ("team/a.b_c__d-e---f", "docker.io/team/a.b_c__d-e---f:latest"),
    ("team/policy:V1_rc.2-x", "docker.io/team/policy:V1_rc.2-x"),
    ("team/policy:_", "docker.io/team/policy:_"),
    ("policy:" + "v" * 128, "docker.io/library/policy:" + "v" * 128),
    (f"policy@{SHA256}", f"docker.io/library/policy@{SHA256}"),
    (f"team/policy:v1@{SHA256}", f"docker.io/team/policy:v1@{SHA256}"),
    (f"policy@sha512:{HEX * 2}", f"docker.io/library/policy@sha512:{HEX * 2}"),
    ("host:5000", "docker.io/library/host:5000"),  # docker reads this as name:tag, so do we
    ("a/" + "b" * 243, "docker.io/a/" + "b" * 243 + ":latest"),  # a 255-character name
]


@pytest.mark.parametrize(("text", "canonical"), VALID)
def test_valid_reference_normalises_like_docker(text: str, canonical: str) -> None:
    ref = parse_reference(text)
    assert str(ref) == canonical
    assert parse_reference(canonical) == ref


def test_reference_fields_and_pinned_form() -> None:
    ref = parse_reference("registry.example.org:5000/team/policy:v3")
    assert ref == ImageReference(
        domain="registry.example.org:5000", path="team/policy", tag="v3", digest=None
    )
    assert ref.name == "registry.example.org:5000/team/policy"
    assert ref.pinned(SHA256) == f"registry.example.org:5000/team/policy@{SHA256}"


def test_reference_with_digest_only_has_no_tag() -> None:
    ref = parse_reference(f"team/policy@{SHA256}")
    assert (ref.tag, ref.digest) == (None, SHA256)


def test_pinned_refuses_a_malformed_digest() -> None:
    with pytest.raises(ImageReferenceError, match="64 lowercase hex"):
        parse_reference("team/policy").pinned("sha256:abc")


INVALID = [
    ("", "empty"),
    ("Ubuntu", "must be lowercase"),
    ("team/Policy:v1", "must be lowercase"),
    ("registry.example.org/Team/policy", "must be lowercase"),
    ("docker.io/Ubuntu", "must be lowercase"),
    ("pölicy", "not ASCII"),
    ("team/policy:v1\u200b", "not ASCII"),
    ("team/policy:v1 ", "whitespace"),
    ("team/\tpolicy", "whitespace"),
    ("team/policy\x07", "control character"),
    ("team/policy\x7f", "control character"),
    ("policy:" + "v" * 129, "tag longer than 128 characters"),
    ("policy:", "tag is empty"),
    ("policy:-v1", "must start with a letter, digit or '_'"),
    ("policy:.v1", "must start with a letter, digit or '_'"),
    ("policy:v1!", "contains '!'"),
    ("policy:v1:v2", "contains ':'"),
    ("team//policy", "empty component"),
    ("team/policy/", "empty component"),
    ("/policy", "empty component"),
    ("team/-policy", "start and end with a letter or digit"),
    ("team/policy.", "start and end with a letter or digit"),
    ("team/a..b", "invalid separator"),
    ("team/a___b", "invalid separator"),
    ("team/a._b", "invalid separator"),
    ("team/a$b", r"contains '\$'"),
    ("exa_mple.com/policy", "invalid registry address"),
    ("-example.com/policy", "invalid registry address"),
    ("example-.com/policy", "invalid registry address"),
    ("example.com:port/policy", "invalid registry address"),
    ("example.com:/policy", "invalid registry address"),
    ("[::1/policy", "invalid registry address"),
    ("[fe80::1%25eth0]:5000/policy", "invalid registry address"),
    ("policy@sha256:abc", "64 lowercase hex digits"),
    (f"policy@sha256:{HEX.upper()}", "64 lowercase hex digits"),
    (f"policy@sha256:{HEX}0", "64 lowercase hex digits"),
    (f"policy@md5:{HEX[:32]}", "unsupported digest algorithm 'md5'"),
    (f"policy@{HEX}", "must look like sha256:"),
    (f"policy@{SHA256}@{SHA256}", "more than one '@'"),
    (f"policy@{SHA256}:v1", "lowercase hex"),
    (HEX, "image ID"),
    ("a/" + "b" * 244, "longer than 255 characters"),
    ("policy:" + "v" * 2000, "longer than 1024 characters"),
]


@pytest.mark.parametrize(("text", "message"), INVALID)
def test_invalid_reference_says_why(text: str, message: str) -> None:
    with pytest.raises(ImageReferenceError, match=message):
        parse_reference(text)


def test_reference_error_is_a_value_error_and_an_image_error() -> None:
    with pytest.raises(ValueError, match="empty") as caught:
        parse_reference("")
    assert isinstance(caught.value, ImageError)


def _check_round_trip(text: str) -> ImageReference | None:
    try:
        ref = parse_reference(text)
    except ImageReferenceError:
        return None
    canonical = str(ref)
    assert re.fullmatch(ORACLE, text)
    assert re.fullmatch(ORACLE, canonical)
    assert parse_reference(canonical) == ref
    assert len(ref.name) <= 255
    assert ref.tag is not None or ref.digest is not None
    return ref


ALPHABET = "ab09Z:/.@_-[]"


@settings(max_examples=500, deadline=None)
@given(st.one_of(st.text(), st.text(alphabet=ALPHABET, max_size=40)))
def test_any_text_parses_or_raises_reference_error(text: str) -> None:
    _check_round_trip(text)


def docker_normalised(text: str) -> str:
    """What ParseNormalizedNamed hands to Parse: the input with docker's domain rule applied."""
    first, slash, _ = text.partition("/")
    if not slash:
        return f"docker.io/library/{text}"
    if first == "localhost" or "." in first or ":" in first or first != first.lower():
        return text
    return f"docker.io/{text}"


def _joined(part: st.SearchStrategy[str], glue: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    """``part (glue part)*`` as a strategy."""
    rest = st.lists(st.tuples(glue, part).map("".join), max_size=4).map("".join)
    return st.tuples(part, rest).map("".join)


def _grammar_references() -> st.SearchStrategy[str]:
    """Strings of the reference grammar, built piece by piece (from_regex is too slow here)."""
    alphanumeric = st.text("abz019", min_size=1, max_size=70)
    separator = st.sampled_from([".", "_", "__", "-", "---"])
    component = _joined(alphanumeric, separator)
    path = _joined(component, st.just("/"))
    label = st.from_regex(r"[a-zA-Z0-9](?:[a-zA-Z0-9-]{0,3}[a-zA-Z0-9])?", fullmatch=True)
    host = st.one_of(
        _joined(label, st.just(".")),
        st.text("0f9A:", min_size=1, max_size=8).map(lambda address: f"[{address}]"),
    )
    port = st.one_of(st.just(""), st.integers(0, 99999).map(lambda n: f":{n}"))
    domain = st.one_of(st.just(""), st.tuples(host, port).map(lambda hp: f"{hp[0]}{hp[1]}/"))
    tag_text = st.from_regex(r"[a-zA-Z0-9_][a-zA-Z0-9_.-]{0,127}", fullmatch=True)
    tag = st.one_of(st.just(""), tag_text.map(lambda t: f":{t}"))
    algorithm = st.sampled_from(["sha256", "sha512", "sha384", "md5", "sha256+b64", "SHA256"])
    encoded = st.one_of(
        st.sampled_from([HEX, HEX * 2, HEX + HEX[:32]]), st.text("0a9F", min_size=32, max_size=130)
    )
    digest = st.one_of(st.just(""), st.tuples(algorithm, encoded).map(lambda d: f"@{d[0]}:{d[1]}"))
    return st.tuples(domain, path, tag, digest).map("".join)


@settings(max_examples=300, deadline=None)
@given(_grammar_references())
def test_what_the_grammar_matches_is_accepted_unless_a_library_rule_refuses(text: str) -> None:
    assert re.fullmatch(ORACLE, text)
    if _check_round_trip(text) is not None:
        return
    with pytest.raises(ImageReferenceError) as caught:
        parse_reference(text)
    if re.fullmatch(ORACLE, docker_normalised(text)):
        assert any(rule in str(caught.value) for rule in EXTRA_RULES), str(caught.value)


# Pure pieces -----------------------------------------------------------------------------------


def test_challenge_with_commas_inside_quotes_parses() -> None:
    header = (
        'Bearer realm="https://auth.example.org/token",service="registry.example.org",'
        'scope="repository:team/policy:pull,push"'
    )
    assert parse_challenge(header) == (
        "bearer",
        {
            "realm": "https://auth.example.org/token",
            "service": "registry.example.org",
            "scope": "repository:team/policy:pull,push",
        },
    )


def test_digest_is_checked_against_expected_and_claimed() -> None:
    body = b'{"schemaVersion": 2}'
    digest = sha256_digest(body)
    assert verify_digest(body, claimed=digest, expected=None) == digest
    assert verify_digest(body, claimed=None, expected=digest) == digest
    sha512 = f"sha512:{hashlib.sha512(body).hexdigest()}"
    assert verify_digest(body, claimed=digest, expected=sha512) == sha512
    with pytest.raises(InvalidManifest, match="does not match"):
        verify_digest(body, claimed=SHA256, expected=None)
    with pytest.raises(InvalidManifest, match="does not match"):
        verify_digest(body, claimed=digest, expected=SHA256)


def test_image_size_is_config_plus_layers() -> None:
    manifest = {
        "config": {"digest": SHA256, "size": 10},
        "layers": [{"digest": SHA256, "size": 1000}, {"digest": SHA256, "size": 5}],
    }
    assert image_size(manifest, what="x") == 1015


@pytest.mark.parametrize(
    "manifest",
    [
        {"config": {"digest": SHA256, "size": 1}},
        {"config": {"digest": SHA256, "size": 1}, "layers": {}},
        {"layers": []},
        {"config": {"digest": SHA256, "size": -1}, "layers": []},
        {"config": {"digest": SHA256, "size": True}, "layers": []},
        {"config": {"digest": SHA256, "size": 1.5}, "layers": []},
        {"config": {"digest": "sha256:zz", "size": 1}, "layers": []},
        {"config": {"digest": SHA256, "size": 1}, "layers": ["x"]},
    ],
)
def test_malformed_manifest_is_invalid(manifest: dict[str, object]) -> None:
    with pytest.raises(InvalidManifest):
        image_size(manifest, what="x")


def test_index_without_linux_amd64_names_the_platforms_it_has() -> None:
    index = {
        "manifests": [
            {"digest": SHA256, "size": 1, "platform": {"os": "linux", "architecture": "arm64"}},
            {"digest": SHA256, "size": 1, "platform": {"os": "windows", "architecture": "amd64"}},
            {"digest": SHA256, "size": 1},
        ]
    }
    with pytest.raises(UnsupportedPlatform, match=r"linux/amd64.*linux/arm64, windows/amd64"):
        amd64_entry(index, what="x")


# Against the real registry ----------------------------------------------------------------------


@dataclass(frozen=True)
class Pushed:
    oci: PushedImage
    docker: PushedImage
    index: PushedImage
    index_amd64: PushedImage
    manifest_list: PushedImage
    list_amd64: PushedImage


@pytest.fixture(scope="module")
def pushed(registry: LocalRegistry) -> Pushed:
    """The module's images, pushed once by the distribution API."""
    with httpx.Client(base_url=registry.url, timeout=10) as http:
        oci = push_image(http, "team/policy", "v1", layer_sizes=[3000, 5000])
        docker = push_image(
            http, "team/docker", "v1", layer_sizes=[7000], media_type=DOCKER_MANIFEST
        )
        arm64 = push_image(http, "team/multi", "arm64", layer_sizes=[100], architecture="arm64")
        amd64 = push_image(http, "team/multi", "amd64", layer_sizes=[20_000, 400])
        index = push_index(
            http, "team/multi", "v1", [("linux/arm64", arm64), ("linux/amd64", amd64)]
        )
        list_amd64 = push_image(
            http, "team/list", "amd64", layer_sizes=[900], media_type=DOCKER_MANIFEST
        )
        manifest_list = push_index(
            http, "team/list", "v1", [("linux/amd64", list_amd64)], media_type=DOCKER_MANIFEST_LIST
        )
        arm_only = push_image(http, "team/arm", "arm64", layer_sizes=[10], architecture="arm64")
        push_index(http, "team/arm", "v1", [("linux/arm64", arm_only)])
    return Pushed(oci, docker, index, amd64, manifest_list, list_amd64)


def resolve(where: LocalRegistry, image: str, *, max_bytes: int = 100 * MB) -> ResolvedImage:
    """Resolve on ``where``, its token service allowed too."""
    allowed = [where.domain]
    if where.realm:
        allowed.append(httpx.URL(where.realm).netloc.decode())
    client = RegistryClient(
        allowed_registries=allowed, insecure_registries=[where.domain], timeout=5.0
    )
    return client.resolve(parse_reference(f"{where.domain}/{image}"), max_bytes=max_bytes)


@pytest.mark.parametrize(
    ("image", "which"), [("team/policy:v1", "oci"), ("team/docker:v1", "docker")]
)
def test_resolve_pins_the_digest_of_the_pushed_manifest_bytes(
    registry: LocalRegistry,
    pushed: Pushed,
    image: str,
    which: str,
) -> None:
    expected: PushedImage = getattr(pushed, which)
    resolved = resolve(registry, image)
    assert resolved.digest == sha256_digest(expected.manifest)
    assert resolved.size_bytes == expected.size_bytes > 7000
    assert resolved.pinned == f"{registry.domain}/{expected.repository}@{resolved.digest}"
    assert resolved.reference == parse_reference(f"{registry.domain}/{image}")


@pytest.mark.parametrize(
    ("image", "index", "amd64"),
    [("team/multi:v1", "index", "index_amd64"), ("team/list:v1", "manifest_list", "list_amd64")],
)
def test_index_is_pinned_and_sized_by_its_linux_amd64_image(
    registry: LocalRegistry,
    pushed: Pushed,
    image: str,
    index: str,
    amd64: str,
) -> None:
    pinned: PushedImage = getattr(pushed, index)
    measured: PushedImage = getattr(pushed, amd64)
    resolved = resolve(registry, image)
    assert resolved.digest == sha256_digest(pinned.manifest)
    assert resolved.size_bytes == measured.size_bytes
    assert resolved.pinned.endswith(f"@{resolved.digest}")


def test_resolve_by_digest_ignores_the_tag(registry: LocalRegistry, pushed: Pushed) -> None:
    for image in (f"team/multi@{pushed.index.digest}", f"team/multi:gone@{pushed.index.digest}"):
        resolved = resolve(registry, image)
        assert (resolved.digest, resolved.size_bytes) == (
            pushed.index.digest,
            pushed.index_amd64.size_bytes,
        )


@pytest.mark.parametrize(
    "image", ["team/policy:v2", "team/ghost:v1", f"team/policy@{SHA256}", "library/policy:v1"]
)
def test_missing_tag_repository_or_digest_is_not_found(
    registry: LocalRegistry,
    pushed: Pushed,
    image: str,
) -> None:
    with pytest.raises(ImageNotFound, match=r"was not found on 127\.0\.0\.1"):
        resolve(registry, image)


def test_index_without_linux_amd64_is_refused(registry: LocalRegistry, pushed: Pushed) -> None:
    with pytest.raises(UnsupportedPlatform, match=r"no linux/amd64 image \(it has: linux/arm64\)"):
        resolve(registry, "team/arm:v1")


def test_image_over_the_limit_is_too_large_with_both_sizes_in_mb(
    registry: LocalRegistry,
    pushed: Pushed,
) -> None:
    size = pushed.index_amd64.size_bytes
    assert resolve(registry, "team/multi:v1", max_bytes=size).size_bytes == size
    with pytest.raises(ImageTooLarge) as caught:
        resolve(registry, "team/multi:v1", max_bytes=20_000)
    expected_size = f"{size / MB:.3g} MB"
    assert f"is {expected_size} (compressed), over the limit of 0.02 MB" in str(caught.value)


def test_other_registry_is_not_allowed_and_never_contacted() -> None:
    def refuse(request: httpx.Request) -> httpx.Response:
        raise AssertionError(f"unexpected request to {request.url}")

    client = RegistryClient(
        allowed_registries=["127.0.0.1:5000", "ghcr.io"], transport=httpx.MockTransport(refuse)
    )
    for image in ("evil.example.org/team/policy:v1", "team/policy", "127.0.0.1:5001/policy"):
        with pytest.raises(RegistryNotAllowed, match=r"allowed registry \(127.0.0.1:5000, ghcr"):
            client.resolve(parse_reference(image), max_bytes=MB)


def test_registry_that_is_down_is_unavailable_at_once() -> None:
    domain = f"127.0.0.1:{free_port()}"
    # At once: a client that waited for its timeout (an hour) would run into the suite's.
    client = RegistryClient(allowed_registries=[domain], insecure_registries=[domain], timeout=3600)
    with pytest.raises(RegistryUnavailable, match=f"cannot reach registry {domain}"):
        client.resolve(parse_reference(f"{domain}/team/policy:v1"), max_bytes=MB)


def test_registry_not_listed_as_insecure_is_spoken_to_over_https(
    registry: LocalRegistry,
    pushed: Pushed,
) -> None:
    client = RegistryClient(allowed_registries=[registry.domain], timeout=5)
    with pytest.raises(RegistryUnavailable, match="cannot reach registry"):
        client.resolve(parse_reference(f"{registry.domain}/team/policy:v1"), max_bytes=MB)


def test_anonymous_bearer_token_is_fetched_once_per_resolve(
    token_registry: LocalRegistry,
    pushed: Pushed,
) -> None:
    assert httpx.get(f"{token_registry.url}/v2/team/multi/manifests/v1").status_code == 401
    before = len(token_registry.token_requests)
    resolved = resolve(token_registry, "team/multi:v1")
    assert (resolved.digest, resolved.size_bytes) == (
        pushed.index.digest,
        pushed.index_amd64.size_bytes,
    )
    assert token_registry.token_requests[before:] == [
        {"service": "manieval-test-registry", "scope": "repository:team/multi:pull"}
    ]


def test_missing_image_behind_token_auth_is_not_found(
    token_registry: LocalRegistry,
    pushed: Pushed,
) -> None:
    with pytest.raises(ImageNotFound):
        resolve(token_registry, "team/ghost:v1")


# Answers a real registry does not give: tampered, oversized, malformed ------------------------

Route = tuple[int, bytes, Mapping[str, str]]


@dataclass
class FakeRegistry:
    """Serves fixed answers by URL path; everything else is MANIFEST_UNKNOWN."""

    routes: dict[str, Route]
    seen: list[str] = field(default_factory=list)

    def handle(self, request: httpx.Request) -> httpx.Response:
        self.seen.append(str(request.url))
        status, body, headers = self.routes.get(
            request.url.path, (404, b'{"errors": [{"code": "MANIFEST_UNKNOWN"}]}', {})
        )
        return httpx.Response(status, content=body, headers=headers)

    def resolve(
        self, image: str, *, max_bytes: int = MB, allowed: tuple[str, ...] = ("auth.test",)
    ) -> ResolvedImage:
        client = RegistryClient(
            allowed_registries=["registry.test", *allowed],
            transport=httpx.MockTransport(self.handle),
        )
        return client.resolve(parse_reference(f"registry.test/{image}"), max_bytes=max_bytes)


def manifest_bytes(*, layer_size: int = 100) -> bytes:
    return json.dumps(
        {
            "schemaVersion": 2,
            "mediaType": OCI_MANIFEST,
            "config": {"digest": SHA256, "size": 10},
            "layers": [{"digest": SHA256, "size": layer_size}],
        }
    ).encode()


def served(body: bytes, *, digest: str | None = None, media_type: str = OCI_MANIFEST) -> Route:
    headers = {"Content-Type": media_type}
    if digest is not None:
        headers["Docker-Content-Digest"] = digest
    return (200, body, headers)


def test_fake_registry_serves_what_resolve_accepts() -> None:
    body = manifest_bytes()
    fake = FakeRegistry({"/v2/team/policy/manifests/v1": served(body, digest=sha256_digest(body))})
    assert fake.resolve("team/policy:v1").size_bytes == 110
    assert fake.seen == ["https://registry.test/v2/team/policy/manifests/v1"]


def test_digest_header_that_does_not_match_the_bytes_is_refused() -> None:
    body = manifest_bytes()
    claimed = sha256_digest(manifest_bytes(layer_size=1))
    fake = FakeRegistry({"/v2/team/policy/manifests/v1": served(body, digest=claimed)})
    with pytest.raises(InvalidManifest, match=f"expected {claimed}"):
        fake.resolve("team/policy:v1")


def test_bytes_that_do_not_match_the_requested_digest_are_refused() -> None:
    asked = sha256_digest(manifest_bytes(layer_size=1))
    fake = FakeRegistry({f"/v2/team/policy/manifests/{asked}": served(manifest_bytes())})
    with pytest.raises(InvalidManifest, match="does not match its digest"):
        fake.resolve(f"team/policy@{asked}")


def test_index_entry_whose_manifest_was_swapped_is_refused() -> None:
    listed, swapped = manifest_bytes(layer_size=1), manifest_bytes(layer_size=2)
    entry = {
        "mediaType": OCI_MANIFEST,
        "digest": sha256_digest(listed),
        "size": len(listed),
        "platform": {"os": "linux", "architecture": "amd64"},
    }
    index = json.dumps({"schemaVersion": 2, "mediaType": OCI_INDEX, "manifests": [entry]})
    fake = FakeRegistry(
        {
            "/v2/team/multi/manifests/v1": served(index.encode(), media_type=OCI_INDEX),
            f"/v2/team/multi/manifests/{entry['digest']}": served(swapped),
        }
    )
    with pytest.raises(InvalidManifest, match="does not match its digest"):
        fake.resolve("team/multi:v1")


def test_index_entry_that_is_another_index_is_refused() -> None:
    inner = json.dumps({"schemaVersion": 2, "mediaType": OCI_INDEX, "manifests": []}).encode()
    entry = {
        "mediaType": OCI_INDEX,
        "digest": sha256_digest(inner),
        "size": len(inner),
        "platform": {"os": "linux", "architecture": "amd64"},
    }
    index = json.dumps({"schemaVersion": 2, "mediaType": OCI_INDEX, "manifests": [entry]})
    fake = FakeRegistry(
        {
            "/v2/team/multi/manifests/v1": served(index.encode(), media_type=OCI_INDEX),
            f"/v2/team/multi/manifests/{entry['digest']}": served(inner, media_type=OCI_INDEX),
        }
    )
    with pytest.raises(InvalidManifest, match="not an image manifest"):
        fake.resolve("team/multi:v1")


@pytest.mark.parametrize(
    ("body", "media_type", "message"),
    [
        (b" " * (4 * 1024 * 1024 + 1), OCI_MANIFEST, "larger than 4.19 MB"),
        (b"<html>hello</html>", "text/html", "not valid JSON"),
        (b"[" * 100_000, OCI_MANIFEST, "not valid JSON"),
        (b"[]", OCI_MANIFEST, "not a JSON object"),
        (
            b'{"schemaVersion": 1, "name": "team/policy", "fsLayers": []}',
            "application/vnd.docker.distribution.manifest.v1+prettyjws",
            "unsupported media type",
        ),
        (b'{"schemaVersion": 2, "mediaType": ["x"]}', OCI_MANIFEST, "unsupported media type"),
        (b'{"schemaVersion": 2, "config": {}}', OCI_MANIFEST, "no layer list"),
    ],
)
def test_malformed_manifest_is_invalid_not_a_crash(
    body: bytes, media_type: str, message: str
) -> None:
    fake = FakeRegistry({"/v2/team/policy/manifests/v1": served(body, media_type=media_type)})
    with pytest.raises(InvalidManifest, match=message):
        fake.resolve("team/policy:v1")


@pytest.mark.parametrize(
    ("status", "error", "message"),
    [
        (500, RegistryUnavailable, "answered HTTP 500"),
        (429, RegistryUnavailable, "answered HTTP 429"),
        (400, RegistryUnavailable, "answered HTTP 400"),
        (403, ImageNotFound, "not public"),
    ],
)
def test_registry_errors_map_to_image_errors(
    status: int, error: type[ImageError], message: str
) -> None:
    route: Route = (status, b'{"errors": [{"code": "X", "message": "went wrong"}]}', {})
    fake = FakeRegistry({"/v2/team/policy/manifests/v1": route})
    with pytest.raises(error, match=f"{message}.*went wrong"):
        fake.resolve("team/policy:v1")


def challenge(header: str) -> Route:
    return (401, b'{"errors": [{"code": "UNAUTHORIZED"}]}', {"WWW-Authenticate": header})


def test_basic_auth_registry_is_refused_as_not_public() -> None:
    fake = FakeRegistry({"/v2/team/policy/manifests/v1": challenge('Basic realm="x"')})
    with pytest.raises(ImageNotFound, match="only public images"):
        fake.resolve("team/policy:v1")


def test_token_service_over_plain_http_is_not_used_for_an_https_registry() -> None:
    header = 'Bearer realm="http://auth.test/token",service="registry.test"'
    fake = FakeRegistry({"/v2/team/policy/manifests/v1": challenge(header)})
    with pytest.raises(RegistryUnavailable, match="not https"):
        fake.resolve("team/policy:v1")
    assert not any("auth.test" in url for url in fake.seen)


def test_token_that_is_still_refused_means_not_public() -> None:
    header = 'Bearer realm="https://auth.test/token",service="registry.test"'
    fake = FakeRegistry(
        {
            "/v2/team/policy/manifests/v1": challenge(header),
            "/token": (200, b'{"access_token": "t"}', {}),
        }
    )
    with pytest.raises(ImageNotFound, match="not public"):
        fake.resolve("team/policy:v1")
    assert fake.seen[1] == (
        "https://auth.test/token?service=registry.test&scope=repository%3Ateam%2Fpolicy%3Apull"
    )
    assert len(fake.seen) == 3  # one token, one retry


# Token realms must be allowed too (issue 13) -------------------------------------------------


def test_token_realm_off_the_allow_list_is_never_asked() -> None:
    header = 'Bearer realm="https://evil.test/token",service="registry.test"'
    fake = FakeRegistry(
        {
            "/v2/team/policy/manifests/v1": challenge(header),
            "/token": (200, b'{"token": "t"}', {}),
        }
    )
    with pytest.raises(RegistryNotAllowed, match=r"token to evil\.test, which is not an allowed"):
        fake.resolve("team/policy:v1")
    assert not any("evil.test" in url for url in fake.seen)


def test_real_registry_with_its_token_service_off_the_allow_list_is_refused(
    token_registry: LocalRegistry, pushed: Pushed
) -> None:
    before = len(token_registry.token_requests)
    client = RegistryClient(
        allowed_registries=[token_registry.domain],
        insecure_registries=[token_registry.domain],
        timeout=5.0,
    )
    with pytest.raises(RegistryNotAllowed, match="not an allowed registry"):
        client.resolve(parse_reference(f"{token_registry.domain}/team/multi:v1"), max_bytes=MB)
    assert token_registry.token_requests[before:] == []


def test_docker_hub_token_service_is_allowed_with_docker_hub() -> None:
    body = manifest_bytes()
    seen: list[str] = []

    def hub(request: httpx.Request) -> httpx.Response:
        seen.append(f"{request.url.host}{request.url.path}")
        if request.url.host == "auth.docker.io":
            return httpx.Response(200, json={"token": "t"})
        if request.headers.get("Authorization") != "Bearer t":
            realm = 'Bearer realm="https://auth.docker.io/token",service="registry.docker.io"'
            return httpx.Response(401, headers={"WWW-Authenticate": realm})
        return httpx.Response(200, content=body, headers={"Content-Type": OCI_MANIFEST})

    client = RegistryClient(allowed_registries=["docker.io"], transport=httpx.MockTransport(hub))
    assert client.resolve(parse_reference("team/policy:v1"), max_bytes=MB).size_bytes == 110
    assert seen == [
        "registry-1.docker.io/v2/team/policy/manifests/v1",
        "auth.docker.io/token",
        "registry-1.docker.io/v2/team/policy/manifests/v1",
    ]


# A total deadline on every registry request (issue 13) ----------------------------------------


class SlowRegistry:
    """A registry on 127.0.0.1 whose every answer is right but slow: it waits ``pause`` seconds
    before each, or, with ``trickle``, sends each answer one byte every ``pause`` seconds. It
    asks for a token (its realm is itself) before it serves a manifest."""

    def __init__(self, *, pause: float, trickle: bool = False) -> None:
        self.pause, self.trickle = pause, trickle
        self.requests: list[str] = []
        self.stop = threading.Event()
        slow = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                slow.requests.append(self.path)
                message = slow.answer(self.path, self.headers.get("Authorization"))
                chunks = (
                    [message[i : i + 1] for i in range(len(message))] if slow.trickle else [message]
                )
                try:
                    for chunk in chunks:
                        if slow.stop.wait(slow.pause):
                            return
                        self.wfile.write(chunk)
                        self.wfile.flush()
                except OSError:
                    pass  # the client gave up, which is what the test wants

            def log_message(self, format: str, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.server.block_on_close = False
        self.domain = f"127.0.0.1:{self.server.server_address[1]}"

    def answer(self, path: str, authorization: str | None) -> bytes:
        if path.startswith("/token"):
            head, body = "200 OK\r\nContent-Type: application/json", b'{"token": "t"}'
        elif authorization != "Bearer t":
            realm = f'Bearer realm="http://{self.domain}/token",service="slow"'
            head, body = f"401 Unauthorized\r\nWWW-Authenticate: {realm}", b"{}"
        else:
            head, body = f"200 OK\r\nContent-Type: {OCI_MANIFEST}", manifest_bytes()
        # The handler closes the connection after each answer, and says so: a client that
        # reused it would race the close (on a busy machine the next request lost).
        length = f"Content-Length: {len(body)}\r\nConnection: close"
        return f"HTTP/1.1 {head}\r\n{length}\r\n\r\n".encode() + body

    def resolve(self, *, timeout: float) -> ResolvedImage:
        client = RegistryClient(
            allowed_registries=[self.domain], insecure_registries=[self.domain], timeout=timeout
        )
        return client.resolve(parse_reference(f"{self.domain}/team/policy:v1"), max_bytes=MB)

    def __enter__(self) -> SlowRegistry:
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stop.set()
        self.server.shutdown()
        self.server.server_close()


def test_slow_but_steady_registry_answers_within_the_deadline() -> None:
    with SlowRegistry(pause=0.05) as slow:
        assert slow.resolve(timeout=30).size_bytes == 110
    manifest = "/v2/team/policy/manifests/v1"
    token = "/token?service=slow&scope=repository%3Ateam%2Fpolicy%3Apull"
    assert slow.requests == [manifest, token, manifest]


def test_three_hops_each_within_the_timeout_share_one_deadline() -> None:
    # Each answer comes well within the timeout, as httpx counts it; all three do not.
    with SlowRegistry(pause=1.2) as slow, pytest.raises(RegistryUnavailable, match="within 2 s"):
        slow.resolve(timeout=2)
    assert len(slow.requests) == 2  # the manifest, the token; no third request was made


def test_registry_trickling_its_answer_byte_by_byte_is_cut_at_the_deadline() -> None:
    # About 110 bytes at 3 s each: every read succeeds, the whole answer would take 330 s, past
    # the suite's timeout; cut at the deadline, it takes about one pause.
    with SlowRegistry(pause=3.0, trickle=True) as slow, pytest.raises(RegistryUnavailable):
        slow.resolve(timeout=1)
