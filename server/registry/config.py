"""The configuration of the service's own registry (CNCF distribution, ``docker-registry``).

A pure builder: the embedded supervisor (``manieval/service.py``) writes it to a file and starts
``docker-registry serve FILE``; ``k8s/base/registry.yaml`` holds the same shape as a ConfigMap.
JSON is YAML, so a caller may ``json.dump`` the result.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

TOKEN_PATH = "/registry/token"
"""The token endpoint's path on the ManiEval server: ``realm = <server URL> + TOKEN_PATH``."""


def registry_config(
    *,
    addr: str,
    storage: Path,
    realm: str,
    cert_path: Path,
    service: str,
    issuer: str,
    http_secret: str | None = None,
) -> dict[str, Any]:
    """A distribution config: token auth against ManiEval, filesystem storage, delete on.

    ``realm`` is the token endpoint's URL (``<server>/registry/token``), ``service`` and
    ``issuer`` must equal the server's ``registry_service`` and ``registry_issuer`` settings,
    ``cert_path`` is the certificate of the signing key (:mod:`server.registry.keys`).
    ``http_secret`` signs upload state; set it when several registry replicas share storage.
    """
    http: dict[str, Any] = {"addr": addr, "headers": {"X-Content-Type-Options": ["nosniff"]}}
    if http_secret is not None:
        http["secret"] = http_secret
    return {
        "version": "0.1",
        "log": {"level": "info", "accesslog": {"disabled": True}},
        "storage": {
            "filesystem": {"rootdirectory": str(storage)},
            "delete": {"enabled": True},
            "maintenance": {
                "uploadpurging": {
                    "enabled": True,
                    "age": "24h",
                    "interval": "1h",
                    "dryrun": False,
                }
            },
        },
        "http": http,
        "auth": {
            "token": {
                "realm": realm,
                "service": service,
                "issuer": issuer,
                "rootcertbundle": str(cert_path),
            }
        },
    }
