"""Request and response bodies of the accounts API: registration, login, sessions, tokens."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from server.kit import security
from server.kit.schemas import InBody, Line

USERNAME_PATTERN = rf"^{security.USERNAME_GRAMMAR}$"  # as security.validate_username
# As service.validate_email, which enforces it with a message for people: printable ASCII,
# one "@", a domain holding a dot but neither starting nor ending with one.
EMAIL_PATTERN = r"^[!-?A-~]+@[!-\-/-?A-~][!-?A-~]*\.[!-?A-~]*[!-\-/-?A-~]$"


class RegisterIn(InBody):
    username: str = Field(
        min_length=3,
        max_length=32,
        pattern=USERNAME_PATTERN,
        description="lowercase letters, digits, '-' and '_'; some names are reserved",
    )
    email: str = Field(
        min_length=3,
        max_length=254,
        json_schema_extra={"format": "email", "pattern": EMAIL_PATTERN},
        description="printable ASCII: one '@', a domain with a dot",
    )
    password: str = Field(
        min_length=security.MIN_PASSWORD_LENGTH,
        max_length=security.MAX_PASSWORD_LENGTH,
        description="at least as strong as the server's minimum zxcvbn score (default 3 of 4); "
        "a 422 says why a password is too weak",
    )


class LoginIn(InBody):
    login: Line = Field(min_length=1, max_length=320, description="username or email")
    password: str = Field(max_length=1024)


class TokenLoginIn(LoginIn):
    name: Line = Field(default="cli", min_length=1, max_length=64)


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
    name: Line = Field(min_length=1, max_length=64)


class TokenOut(BaseModel):
    id: int
    name: str
    prefix: str
    created_at: datetime
    last_used_at: datetime | None
    revoked_at: datetime | None


class NewTokenOut(TokenOut):
    token: str = Field(description="shown once: store it now")
