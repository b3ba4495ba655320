"""What the registry token endpoint answers (the Docker registry token specification)."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field


class RegistryTokenOut(BaseModel):
    token: str = Field(description="A JWT the registry accepts as `Authorization: Bearer`.")
    access_token: str = Field(description="The same token, for OAuth 2.0 clients.")
    expires_in: int = Field(description="Seconds the token is valid.")
    issued_at: datetime


class RegistryOut(BaseModel):
    domain: str = Field(
        description="Where participants push: `<domain>/<user>/<name>:<tag>` (`manieval push`)."
    )
