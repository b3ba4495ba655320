"""What the service publishes in its own registry for every participant to build on: the policy
base image (docker/policy-base), as ``<registry>/manieval/policy-base:bookworm``.

Every registry login may pull it and nobody pushes there but the server (tokens.py,
:data:`~server.registry.tokens.SERVICE_NAMESPACE`): `manieval serve` and `manieval demo` copy the
base their engine holds into the registry they embed, and an operator of another registry copies
it with a token from ``manieval admin publish-token`` (docs/registry.md). The getting-started
and submit pages name it, pinned by digest, when the registry has it.
"""

from __future__ import annotations

from server.registry.tokens import SERVICE_NAMESPACE

LOCAL_POLICY_BASE = "localhost/manieval-base:bookworm"
"""The base as docker/policy-base/build.sh (and `make install`) tags it in the local engine."""
POLICY_BASE_REPOSITORY = f"{SERVICE_NAMESPACE}/policy-base"
POLICY_BASE_TAG = "bookworm"


def policy_base(domain: str) -> str:
    """The published base on the registry at `domain`, by tag."""
    return f"{domain}/{POLICY_BASE_REPOSITORY}:{POLICY_BASE_TAG}"
