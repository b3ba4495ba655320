"""Registry tokens (the Docker registry token specification), as pure rules and a signer.

A client asks for scopes such as ``repository:alice/policy:push,pull``; :func:`grant` keeps
what the caller may have and drops the rest, as the specification wants (the registry then
answers ``denied``). :class:`TokenSigner` signs the granted access into a JWT the registry
verifies through the ``x5c`` certificate chain against its ``rootcertbundle``.
"""

from __future__ import annotations

import datetime as dt
import re
import secrets
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import jwt

from server.registry.keys import SigningKey

_ACTIONS = ("pull", "push")
# distribution/reference's path grammar: what a repository name may be
_COMPONENT = r"[a-z0-9]+(?:(?:[._]|__|-+)[a-z0-9]+)*"
_COMPONENT_RE = re.compile(_COMPONENT, re.ASCII)
_REPOSITORY_RE = re.compile(rf"{_COMPONENT}(?:/{_COMPONENT})*", re.ASCII)
MAX_REPOSITORY_LENGTH = 255
MAX_SCOPES = 16  # a push names two or three (the target, mount sources); more is not a client
# What the service itself publishes for everyone to build on (the policy base image): every
# grantee may pull it, nobody pushes but the server (its own tokens, service.server_token). No
# account can own this namespace: the name is reserved (kit/security.RESERVED_USERNAMES).
SERVICE_NAMESPACE = "manieval"


@dataclass(frozen=True)
class Access:
    """One entry of a token's ``access`` claim."""

    type: str
    name: str
    actions: tuple[str, ...]

    def claim(self) -> dict[str, Any]:
        return {"type": self.type, "name": self.name, "actions": list(self.actions)}


@dataclass(frozen=True)
class Grantee:
    """Who asks: a participant (push and pull under their namespace) or the pull credential."""

    subject: str
    namespace: str | None  # the participant's first path component; None for the puller
    pull_anywhere: bool = False


@dataclass(frozen=True)
class IssuedToken:
    token: str
    expires_in: int
    issued_at: dt.datetime


def namespace_for(username: str) -> str | None:
    """The repository namespace of a user name, or None when it is no valid path component."""
    name = username.lower()
    return name if _COMPONENT_RE.fullmatch(name) else None


def valid_repository(name: str) -> bool:
    return len(name) <= MAX_REPOSITORY_LENGTH and _REPOSITORY_RE.fullmatch(name) is not None


def parse_scopes(scopes: Iterable[str]) -> list[Access]:
    """``type[(class)]:name:actions`` scopes (space-separated within one value, too) as access
    requests; malformed ones are dropped, like any scope the caller may not have."""
    requested: list[Access] = []
    for value in scopes:
        for scope in value.split():
            kind, _, rest = scope.partition(":")
            name, _, actions = rest.rpartition(":")
            kind = kind.partition("(")[0]
            if kind and name:
                parts = tuple(sorted({a for a in actions.split(",") if a}))
                requested.append(Access(type=kind, name=name, actions=parts))
            if len(requested) >= MAX_SCOPES:
                return requested
    return requested


def grant(requested: Sequence[Access], grantee: Grantee) -> list[Access]:
    """What ``grantee`` gets of ``requested``: push and pull on its own repositories, pull
    anywhere for the pull credential, pull on the service's own (:data:`SERVICE_NAMESPACE`) for
    everyone, nothing else (no catalog, no delete)."""
    granted: dict[str, set[str]] = {}
    for access in requested:
        if access.type != "repository" or not valid_repository(access.name):
            continue
        allowed: set[str] = set()
        namespace = access.name.split("/")[0]
        if namespace == SERVICE_NAMESPACE or grantee.pull_anywhere:  # first: whatever the name
            allowed = {"pull"}
        elif grantee.namespace is not None and namespace == grantee.namespace:
            allowed = {"pull", "push"}
        actions = allowed & set(access.actions)
        if actions:
            granted.setdefault(access.name, set()).update(actions)
    return [
        Access(type="repository", name=name, actions=tuple(a for a in _ACTIONS if a in actions))
        for name, actions in granted.items()
    ]


class TokenSigner:
    """Signs registry tokens for one registry (``service``) as one ``issuer``."""

    def __init__(self, key: SigningKey, *, service: str, issuer: str, ttl_s: int) -> None:
        self._private = key.private_pem()
        self._x5c = key.x5c()
        self._algorithm = key.algorithm()
        self.service, self.issuer, self.ttl_s = service, issuer, ttl_s

    def issue(
        self, *, subject: str, access: Sequence[Access], now: dt.datetime | None = None
    ) -> IssuedToken:
        """A signed token for ``access``; ``now`` in the past mints one already expired."""
        now = now or dt.datetime.now(dt.UTC)
        issued = int(now.timestamp())
        claims = {
            "iss": self.issuer,
            "sub": subject,
            "aud": self.service,
            "exp": issued + self.ttl_s,
            "nbf": issued - 5,  # a registry's clock a little behind ours
            "iat": issued,
            "jti": secrets.token_urlsafe(16),
            "access": [a.claim() for a in access],
        }
        headers = {"typ": "JWT", "x5c": self._x5c}
        token = jwt.encode(claims, self._private, algorithm=self._algorithm, headers=headers)
        return IssuedToken(token=token, expires_in=self.ttl_s, issued_at=now)
