"""Request and response bodies of the accounts API: registration, login, sessions, tokens, and
the links mailed to verify an address or reset a password."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import BaseModel, Field

from server.kit import security
from server.kit.schemas import InBody, Line

USERNAME_PATTERN = rf"^{security.USERNAME_GRAMMAR}$"  # as security.validate_username
# As service.validate_email, which enforces it with a message for people: printable ASCII,
# one "@", a domain holding a dot but neither starting nor ending with one.
EMAIL_PATTERN = r"^[!-?A-~]+@[!-\-/-?A-~][!-?A-~]*\.[!-?A-~]*[!-\-/-?A-~]$"


Email = Annotated[
    str,
    Field(
        min_length=3,
        max_length=254,
        json_schema_extra={"format": "email", "pattern": EMAIL_PATTERN},
        description="printable ASCII: one '@', a domain with a dot",
    ),
]
NewPassword = Annotated[
    str,
    Field(
        min_length=security.MIN_PASSWORD_LENGTH,
        max_length=security.MAX_PASSWORD_LENGTH,
        description="at least as strong as the server's minimum zxcvbn score (default 3 of 4); "
        "a 422 says why a password is too weak",
    ),
]
LinkToken = Annotated[
    str,
    Field(
        min_length=43,
        max_length=43,
        pattern=r"^[A-Za-z0-9_-]{43}$",
        description="the `token` parameter of the mailed link",
    ),
]


class RegisterIn(InBody):
    """Only sizes are checked here: the server checks the rest itself, so that one answer
    lists every problem of the form, a taken name or address among them."""

    # The rules are stated to clients (the schema) but checked by the server, not here.
    username: str = Field(
        max_length=64,
        description="3 to 32 characters: letters, digits, '-' and '_'; some names are reserved. "
        "Kept as typed, for display; unique and matched at login regardless of case",
        json_schema_extra={"pattern": USERNAME_PATTERN, "minLength": 3, "maxLength": 32},
    )
    email: str = Field(
        max_length=320,
        description="printable ASCII: one '@', a domain with a dot; surrounding blanks are trimmed",
        json_schema_extra={"format": "email"},
    )
    password: str = Field(
        max_length=1024,
        json_schema_extra={"minLength": security.MIN_PASSWORD_LENGTH},
        description=f"{security.MIN_PASSWORD_LENGTH} to {security.MAX_PASSWORD_LENGTH} "
        "characters, at least as strong as the server's minimum zxcvbn score (default 3 of 4)",
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
    email_verified: bool = Field(
        description="whether the owner followed a link mailed to `email`; some servers "
        "accept submissions only then"
    )
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


class VerifyIn(InBody):
    token: LinkToken


class PasswordResetIn(InBody):
    email: Email


class PasswordResetConfirmIn(InBody):
    token: LinkToken
    password: NewPassword


class EmailChangeIn(InBody):
    email: Email = Field(description="the new address: it is used once its link is followed")
    current_password: str = Field(max_length=1024)


class MessageOut(BaseModel):
    message: str = Field(description="what happened, for people")
