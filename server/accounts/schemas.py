"""Request and response bodies of the accounts API: registration, login, sessions, tokens."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from server.kit.schemas import InBody


class RegisterIn(InBody):
    username: str = Field(max_length=64)
    email: str = Field(max_length=320)
    password: str = Field(max_length=1024)


class LoginIn(InBody):
    login: str = Field(max_length=320, description="username or email")
    password: str = Field(max_length=1024)


class TokenLoginIn(LoginIn):
    name: str = Field(default="cli", max_length=64)


class UserOut(BaseModel):
    id: int
    username: str
    email: str
    is_admin: bool
    created_at: datetime


class SessionOut(BaseModel):
    user: UserOut
    csrf_token: str


class TokenIn(InBody):
    name: str = Field(max_length=64)


class TokenOut(BaseModel):
    id: int
    name: str
    prefix: str
    created_at: datetime
    last_used_at: datetime | None
    revoked_at: datetime | None


class NewTokenOut(TokenOut):
    token: str = Field(description="shown once: store it now")
