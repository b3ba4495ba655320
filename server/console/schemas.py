"""Bodies of the administrators' accounts API, `/api/v1/admin/users`."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from server.kit.schemas import InBody


class AdminUserOut(BaseModel):
    id: int
    username: str
    email: str
    email_verified: bool
    is_admin: bool
    created_at: datetime
    disabled_at: datetime | None = Field(description="when it was disabled; null: enabled")
    disabled_reason: str | None = Field(description="why, as the account's owner is told")
    submissions: int = Field(description="the participant's own submissions")


class DisabledOut(AdminUserOut):
    cancelled: list[int] = Field(description="its queued and running submissions, cancelled")


class ReasonIn(InBody):
    reason: str = Field(
        default="", max_length=2000, description="why: required to disable, optional to enable"
    )
