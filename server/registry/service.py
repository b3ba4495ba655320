"""The service's own registry: who may have which registry token (docs/registry.md).

Participants log in to the registry with their user name and one of their API tokens, the
workers and Kubernetes nodes with the pull-only credential; the API token is checked at every
token request, so a revoked one stops working when the last token it got expires.
"""

from __future__ import annotations

import base64
import binascii
import secrets
import threading
from collections.abc import Sequence
from pathlib import Path

from sqlalchemy.orm import Session as DB

from server.accounts import service as accounts
from server.kit.errors import Invalid, Unauthorized, Unavailable
from server.kit.settings import Settings
from server.registry.keys import (
    SigningKey,
    SigningKeyMissing,
    ensure_signing_key,
    load_signing_key,
)
from server.registry.tokens import (
    SERVICE_NAMESPACE,
    Access,
    Grantee,
    IssuedToken,
    TokenSigner,
    grant,
    namespace_for,
    parse_scopes,
    valid_repository,
)

BASIC_REALM = "manieval-registry"
SERVER_SUBJECT = "manieval-server"


class RegistryUnauthorized(Unauthorized):
    """No or wrong credentials: the registry client is asked for Basic ones (``docker login``)."""

    def headers(self) -> dict[str, str]:
        return {"WWW-Authenticate": f'Basic realm="{BASIC_REALM}", charset="UTF-8"'}


def key_directory(settings: Settings) -> Path:
    return settings.registry_key_dir or settings.data_dir / "registry-key"


def signing_key(settings: Settings) -> SigningKey:
    """The token signing key: made on first use in dev mode, else it must be there (a Secret)."""
    directory = key_directory(settings)
    if settings.dev_mode and settings.registry_key_dir is None:
        return ensure_signing_key(directory)
    return load_signing_key(directory)


_signers: dict[tuple[object, ...], TokenSigner] = {}
_signers_lock = threading.Lock()


def signer(settings: Settings) -> TokenSigner:
    """The signer of these settings, reloaded when the key files change (a rotated Secret)."""
    try:
        key = signing_key(settings)
    except SigningKeyMissing as exc:  # an installation's mistake: say so, do not crash
        raise Unavailable(f"{exc}; see docs/registry.md") from None
    stamp = tuple(path.stat().st_mtime_ns for path in (key.key_path, key.cert_path))
    cache_key = (
        str(key.key_path),
        stamp,
        settings.registry_service,
        settings.registry_issuer,
        settings.registry_token_ttl_s,
    )
    with _signers_lock:
        found = _signers.get(cache_key)
        if found is None:
            found = TokenSigner(
                key,
                service=settings.registry_service,
                issuer=settings.registry_issuer,
                ttl_s=settings.registry_token_ttl_s,
            )
            _signers.clear()  # one key at a time: the old one is gone with its files
            _signers[cache_key] = found
        return found


def basic_credentials(authorization: str | None) -> tuple[str, str] | None:
    """The user name and password of an ``Authorization: Basic`` header, or None."""
    if authorization is None:
        return None
    scheme, _, value = authorization.strip().partition(" ")
    if scheme.lower() != "basic":
        return None
    try:
        decoded = base64.b64decode(value.strip(), validate=True).decode("utf-8")
    except (binascii.Error, UnicodeDecodeError):
        return None
    user, colon, password = decoded.partition(":")
    return (user, password) if colon and user and password else None


def authenticate(db: DB, *, settings: Settings, username: str, password: str) -> Grantee:
    """The grantee behind these credentials; raises :class:`RegistryUnauthorized`."""
    pull_password = settings.secret("registry_pull_password")
    if secrets.compare_digest(username.encode(), settings.registry_pull_user.encode()):
        if secrets.compare_digest(password.encode(), pull_password.encode()):
            return Grantee(subject=settings.registry_pull_user, namespace=None, pull_anywhere=True)
        raise RegistryUnauthorized("wrong user name or password for the registry")
    try:
        user = accounts.user_for_token(db, plaintext=password)
    except accounts.AccountDisabled as exc:
        raise RegistryUnauthorized(exc.message) from None
    if user is None or user.username.lower() != username.lower():
        raise RegistryUnauthorized(
            "log in to the registry with your ManiEval user name and an API token "
            "(manieval login, or the Tokens page)"
        )
    return Grantee(subject=user.username, namespace=namespace_for(user.username))


def issue_token(
    db: DB,
    *,
    settings: Settings,
    authorization: str | None,
    service: str | None,
    scopes: Sequence[str],
) -> IssuedToken:
    """A token for the scopes the caller may have (possibly none: ``docker login`` asks for
    none); anonymous callers get no token at all."""
    if service is not None and service != settings.registry_service:
        raise Invalid(
            f"this server issues tokens for {settings.registry_service!r}, not {service!r}",
            fields={"service": settings.registry_service},
        )
    credentials = basic_credentials(authorization)
    if credentials is None:
        raise RegistryUnauthorized("the registry needs a user name and an API token")
    grantee = authenticate(db, settings=settings, username=credentials[0], password=credentials[1])
    access = grant(parse_scopes(scopes), grantee)
    return signer(settings).issue(subject=grantee.subject, access=access)


def server_pull_token(settings: Settings, *, repository: str) -> str:
    """A pull token for one repository, minted by the server for itself (pinning a submission)."""
    access = [Access(type="repository", name=repository, actions=("pull",))]
    return signer(settings).issue(subject=SERVER_SUBJECT, access=access).token


def publish_token(settings: Settings, *, repository: str) -> str:
    """A push token for one repository of the service's own namespace (``manieval/...``), the
    only way anything is pushed there: `manieval serve` publishing the policy base, or an
    operator's ``manieval admin publish-token`` (docs/registry.md)."""
    if not (valid_repository(repository) and repository.startswith(f"{SERVICE_NAMESPACE}/")):
        raise ValueError(f"the server publishes only under {SERVICE_NAMESPACE}/, not {repository}")
    access = [Access(type="repository", name=repository, actions=("pull", "push"))]
    return signer(settings).issue(subject=SERVER_SUBJECT, access=access).token
