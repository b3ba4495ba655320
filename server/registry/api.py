"""``GET /registry/token``: the token service of the service's own registry (docs/registry.md).

The registry sends clients here (its ``auth.token.realm``); they authenticate with HTTP Basic,
a ManiEval user name and API token, or the pull-only credential.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from server.kit.deps import DBDep, limit, services
from server.kit.errors import ERROR_RESPONSES, NotFound
from server.registry import service as registry
from server.registry.schemas import RegistryOut, RegistryTokenOut

router = APIRouter(prefix="/registry", responses=ERROR_RESPONSES, tags=["registry"])
public = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES, tags=["registry"])


@public.get("/registry")
def registry_info(request: Request) -> RegistryOut:
    """The service's own registry, where participants push their policy images."""
    domain = services(request).settings.registry_domain
    if domain is None:
        raise NotFound("this service runs no registry of its own")
    return RegistryOut(domain=domain)


@router.get("/token")
def token(
    request: Request,
    db: DBDep,
    service: Annotated[str | None, Query(max_length=255)] = None,
    scope: Annotated[list[str] | None, Query(max_length=16)] = None,
) -> RegistryTokenOut:
    """A registry token for the requested scopes the caller may have; rate-limited per client
    address and per user name."""
    settings = services(request).settings
    if settings.registry_domain is None:
        raise NotFound("this service runs no registry of its own")
    authorization = request.headers.get("authorization")
    credentials = registry.basic_credentials(authorization)
    limit(request, "registry_token", key=(credentials[0].lower() if credentials else ""))
    issued = registry.issue_token(
        db, settings=settings, authorization=authorization, service=service, scopes=scope or []
    )
    db.commit()  # the API token's last use
    return RegistryTokenOut(
        token=issued.token,
        access_token=issued.token,
        expires_in=issued.expires_in,
        issued_at=issued.issued_at,
    )
