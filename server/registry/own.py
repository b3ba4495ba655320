"""The service's own registry as the server's registry client sees it: its address, and a
pull token the server signs for itself (no request to its own token endpoint)."""

from __future__ import annotations

import ipaddress
from collections.abc import Callable
from dataclasses import dataclass

from server.kit.image_refs import canonical_domain
from server.kit.settings import Settings
from server.registry import service


@dataclass(frozen=True)
class OwnRegistry:
    """The service's own registry: where the server reaches it, and how it gets a pull token
    for one repository without asking anyone (it signs them)."""

    domain: str
    base_url: str
    pull_token: Callable[[str], str]


def own_registry_of(settings: Settings) -> OwnRegistry | None:
    """The service's own registry as these settings describe it, or None."""
    if settings.registry_domain is None:
        return None
    domain = canonical_domain(settings.registry_domain)
    scheme = "http" if plain_http(settings, domain) else "https"
    return OwnRegistry(
        domain=domain,
        base_url=(settings.registry_internal_url or f"{scheme}://{domain}").rstrip("/"),
        pull_token=lambda repository: service.server_pull_token(settings, repository=repository),
    )


def plain_http(settings: Settings, domain: str) -> bool:
    """Whether the registry at `domain` is spoken to over plain HTTP: one the settings call
    insecure, or one on the loopback address."""
    domain = canonical_domain(domain)
    insecure = domain in {canonical_domain(d) for d in settings.insecure_registries}
    return insecure or loopback_domain(domain)


def loopback_domain(domain: str) -> bool:
    """Whether a registry's ``HOST[:PORT]`` is on this machine: ``localhost`` or a loopback
    address (127.0.0.0/8, ``[::1]``); a name that merely begins with ``127.`` is not."""
    host = domain.lower().rsplit(":", 1)[0] if not domain.endswith("]") else domain
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
