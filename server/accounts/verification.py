"""Links mailed to an account: verifying an address (on registration, and a new one on an
email change) and resetting a password.

Each link carries a random 256-bit token; the database keeps only its SHA-256 (as API tokens,
server/kit/security.py), so a copy of it opens no account. A token works once (taken by a
conditional update, so two requests racing cannot both use it) and until it expires. Each
function returns the mail to send, which the caller sends after committing
(server/accounts/mail.py); none of them tells whether an address has an account.
"""

from __future__ import annotations

import hashlib
import re
import secrets
from datetime import datetime
from email.message import EmailMessage
from typing import Final, Literal

from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import joinedload

from server.accounts import service as accounts
from server.accounts.mail import Letters
from server.kit import security
from server.kit.errors import Conflict, Invalid
from server.models import User, utcnow
from server.models.accounts import EmailToken

Purpose = Literal["verify", "reset"]
VERIFY: Final = "verify"
RESET: Final = "reset"
BAD_LINK = "This link is not valid: it may have expired or been used already. Ask for a new one."
_TOKEN = re.compile(r"[A-Za-z0-9_-]{43}")


def _digest(plaintext: str) -> str:
    # SHA-256, not argon2: 256 random bits leave nothing to guess, and the digest is the key
    # the row is found by.
    return hashlib.sha256(plaintext.encode("ascii")).hexdigest()


def _issue(db: DB, *, user: User, purpose: Purpose, email: str, letters: Letters) -> str:
    now = utcnow()
    lifetime = letters.verify_for if purpose == VERIFY else letters.reset_for
    plaintext = secrets.token_urlsafe(32)
    db.add(
        EmailToken(
            user_id=user.id,
            purpose=purpose,
            email=email,
            digest=_digest(plaintext),
            created_at=now,
            expires_at=now + lifetime,
        )
    )
    db.flush()
    return plaintext


def _live(db: DB, *, token: str, purpose: Purpose, now: datetime) -> EmailToken | None:
    if not _TOKEN.fullmatch(token):
        return None
    found = db.scalar(
        select(EmailToken)
        .options(joinedload(EmailToken.user))
        .where(EmailToken.digest == _digest(token), EmailToken.purpose == purpose)
    )
    if found is None or found.used_at is not None or found.expires_at <= now:
        return None
    return found


def _use(db: DB, *, token: EmailToken, now: datetime) -> None:
    """Mark `token` used, or Invalid when another request used it first."""
    taken = db.execute(
        update(EmailToken)
        .where(EmailToken.id == token.id, EmailToken.used_at.is_(None))
        .values(used_at=now)
        .execution_options(synchronize_session=False)
    )
    if taken.rowcount != 1:  # type: ignore[attr-defined]
        raise Invalid(BAD_LINK, fields={"token": BAD_LINK})


def _retire(db: DB, *, user: User, purpose: Purpose, now: datetime) -> None:
    """Every unused link of `user` for `purpose` stops working."""
    db.execute(
        update(EmailToken)
        .where(
            EmailToken.user_id == user.id,
            EmailToken.purpose == purpose,
            EmailToken.used_at.is_(None),
        )
        .values(used_at=now)
        .execution_options(synchronize_session=False)
    )


# Verification ---------------------------------------------------------------------------------


def verification_mail(db: DB, *, user: User, letters: Letters) -> EmailMessage | None:
    """A new link to verify the user's address; None when it is verified already."""
    if user.email_verified_at is not None:
        return None
    token = _issue(db, user=user, purpose=VERIFY, email=user.email, letters=letters)
    return letters.verification(username=user.username, email=user.email, token=token, change=False)


def request_email_change(db: DB, *, user: User, new_email: str, letters: Letters) -> EmailMessage:
    """The mail for `new_email`: a link that moves the account there once followed, or, when
    another account has that address, a note saying so (to that address, not to the caller:
    the answer is the same either way). Invalid when the address is malformed or the user's."""
    new_email = accounts.normalise_email(new_email)
    if (problem := accounts.validate_email(new_email)) is not None:
        raise Invalid("the email address is not valid", fields={"email": problem})
    if new_email == user.email:
        raise Invalid("this is your address already", fields={"email": "already your address"})
    if db.scalar(select(User.id).where(User.email == new_email)) is not None:
        return letters.address_in_use(email=new_email)
    # Only the newest request counts: an older link to another address stops working.
    db.execute(
        update(EmailToken)
        .where(
            EmailToken.user_id == user.id,
            EmailToken.purpose == VERIFY,
            EmailToken.used_at.is_(None),
            EmailToken.email != user.email,
        )
        .values(used_at=utcnow())
        .execution_options(synchronize_session=False)
    )
    token = _issue(db, user=user, purpose=VERIFY, email=new_email, letters=letters)
    return letters.verification(username=user.username, email=new_email, token=token, change=True)


def verify_email(db: DB, *, token: str, now: datetime | None = None) -> User:
    """Follow a verification link: its address becomes the account's, verified. Invalid when
    the link is unknown, used or expired; Conflict when another account took the address."""
    now = now or utcnow()
    found = _live(db, token=token, purpose=VERIFY, now=now)
    if found is None:
        raise Invalid(BAD_LINK, fields={"token": BAD_LINK})
    user = found.user
    _use(db, token=found, now=now)
    if found.email != user.email:
        other = db.scalar(select(User.id).where(User.email == found.email, User.id != user.id))
        if other is not None:
            raise Conflict("another account uses this address now", fields={"token": "taken"})
        user.email = found.email
        try:
            db.flush()
        except IntegrityError:  # an account registered with the address a moment ago
            db.rollback()
            raise Conflict(
                "another account uses this address now", fields={"token": "taken"}
            ) from None
        # The account moved: links sent to the old address must not move it back or reset it.
        _retire(db, user=user, purpose=VERIFY, now=now)
        _retire(db, user=user, purpose=RESET, now=now)
        user.email_verified_at = now
    elif user.email_verified_at is None:
        user.email_verified_at = now
    db.flush()
    return user


# Password reset -------------------------------------------------------------------------------


def password_reset_mail(db: DB, *, email: str, letters: Letters) -> EmailMessage | None:
    """A reset link for the account using `email`; None (and nothing stored) when none does."""
    email = accounts.normalise_email(email)
    if (problem := accounts.validate_email(email)) is not None:
        raise Invalid("the email address is not valid", fields={"email": problem})
    user = db.scalar(select(User).where(User.email == email))
    if user is None:
        return None
    token = _issue(db, user=user, purpose=RESET, email=user.email, letters=letters)
    return letters.password_reset(username=user.username, email=user.email, token=token)


def reset_link_works(db: DB, *, token: str, now: datetime | None = None) -> bool:
    """Whether a reset link can still be used (the page shows its form, or says why not)."""
    found = _live(db, token=token, purpose=RESET, now=now or utcnow())
    return found is not None and found.email == found.user.email


def reset_password(
    db: DB,
    *,
    token: str,
    password: str,
    min_score: int = security.DEFAULT_MIN_SCORE,
    now: datetime | None = None,
) -> User:
    """Set a new password through a reset link, which then stops working, as every other
    reset link of the account; every browser session ends. Invalid for a bad link or a weak
    password (the link then still works)."""
    now = now or utcnow()
    found = _live(db, token=token, purpose=RESET, now=now)
    if found is None or found.email != found.user.email:
        raise Invalid(BAD_LINK, fields={"token": BAD_LINK})
    user = found.user
    accounts.set_password(db, user, password, min_score=min_score)
    _use(db, token=found, now=now)
    _retire(db, user=user, purpose=RESET, now=now)
    if user.email_verified_at is None:
        user.email_verified_at = now  # the link reached the address: it is the owner's
    db.flush()
    return user
