"""Accounts: registration, password login, browser sessions and API tokens, and what an
administrator does to an account (disable, enable, verify its address, grant or revoke admin
rights; each leaves an audit record)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import joinedload

from server import audit
from server.kit import security
from server.kit.errors import (
    AppError,
    Conflict,
    Forbidden,
    Invalid,
    NotFound,
    RateLimited,
    Unauthorized,
)
from server.kit.ratelimit import Rate, RateLimiter
from server.models import ApiToken, Session, Submission, User, utcnow

MAX_TOKENS_PER_USER = 50


def normalise_email(email: str) -> str:
    """The stored form of an email address: trimmed and lower-case."""
    return email.strip().lower()


def user_named(db: DB, *, username: str) -> User | None:
    """The account with this user name, whatever its case ("Dora" is "dora")."""
    return db.scalar(select(User).where(func.lower(User.username) == username.strip().lower()))


def register(
    db: DB,
    *,
    username: str,
    email: str,
    password: str,
    admin: bool = False,
    min_score: int = security.DEFAULT_MIN_SCORE,
) -> User:
    """Create an account, or raise Invalid (a field to fix) / Conflict (name or email taken).

    Every problem is reported at once, a taken name or address among them: a 422 when some
    field is malformed, a 409 when the only problem is that the name or address is taken. The
    name keeps the case it is typed in and is unique regardless of case; surrounding blanks
    are trimmed. Its address is unverified (server/accounts/verification.py mails the link),
    except for an administrator's account, which an operator creates and vouches for."""
    username, email = username.strip(), normalise_email(email)
    malformed = _field_problems(username, email, password, min_score=min_score)
    taken: dict[str, str] = {}  # checked only for well-formed fields, so a typo asks nothing
    if "username" not in malformed and user_named(db, username=username) is not None:
        taken["username"] = "already taken"
    if "email" not in malformed and _user_with_email(db, email) is not None:
        taken["email"] = "already taken"
    if malformed:
        raise Invalid("the account cannot be created", fields={**malformed, **taken})
    if taken:
        which = "this username and email are" if len(taken) == 2 else f"this {next(iter(taken))} is"
        raise Conflict(f"{which} already registered", fields=taken)
    user = User(
        username=username,
        email=email,
        password_hash=security.hash_password(password),
        is_admin=admin,
        email_verified_at=utcnow() if admin else None,
    )
    db.add(user)
    try:
        db.flush()
    except IntegrityError:  # a concurrent registration won the race
        db.rollback()
        raise Conflict("this username or email is already registered") from None
    return user


def _field_problems(username: str, email: str, password: str, *, min_score: int) -> dict[str, str]:
    problems: dict[str, str] = {}
    if (problem := security.validate_username(username)) is not None:
        problems["username"] = problem
    if (problem := validate_email(email)) is not None:
        problems["email"] = problem
    if found := security.password_problems(
        password, username=username, email=email, min_score=min_score
    ):
        problems["password"] = " ".join(found)
    return problems


def _user_with_email(db: DB, email: str) -> User | None:
    return db.scalar(select(User).where(User.email == email))


@dataclass(frozen=True)
class RegistrationThrottle:
    """Where registrations from one client address are counted (docs/server.md, Accounts)."""

    limiter: RateLimiter
    accounts: Rate  # accounts created, and answers that an address is taken
    attempts: Rate  # every attempt: bounds the work one address can make the server do
    address: str


def register_counted(
    db: DB,
    *,
    throttle: RegistrationThrottle,
    username: str,
    email: str,
    password: str,
    min_score: int,
) -> User:
    """`register`, rate-limited so that a typo costs nothing: a rejected form counts only as an
    attempt, a created account against the address's accounts. A 409 for a taken address
    counts as an account too, so probing which addresses have accounts stays as slow as it
    was. The caller commits; on RateLimited it must roll back."""
    accounts_key = f"register:ip:{throttle.address}"
    if not (spent := throttle.limiter.peek(accounts_key, throttle.accounts)).allowed:
        raise _too_many(spent.retry_after)
    attempt = throttle.limiter.hit(f"register-attempt:ip:{throttle.address}", throttle.attempts)
    if not attempt.allowed:
        raise _too_many(attempt.retry_after)
    try:
        user = register(db, username=username, email=email, password=password, min_score=min_score)
    except AppError as exc:
        if exc.fields.get("email") == "already taken":
            throttle.limiter.hit(accounts_key, throttle.accounts)
        raise
    if not (counted := throttle.limiter.hit(accounts_key, throttle.accounts)).allowed:
        raise _too_many(counted.retry_after)  # a concurrent registration took the last one
    return user


def _too_many(retry_after: float) -> RateLimited:
    return RateLimited(
        f"too many register requests; try again in {retry_after:.0f} s", retry_after=retry_after
    )


def validate_email(email: str) -> str | None:
    """What is wrong with an email address, for its form field; None when nothing is."""
    if any(c.isspace() for c in email):
        return "an email address cannot contain spaces"
    if len(email) > 254 or email.count("@") != 1:
        return "enter an email address like name@example.org"
    local, _, domain = email.partition("@")
    if not local or "." not in domain or domain.startswith(".") or domain.endswith("."):
        return "enter an email address like name@example.org"
    if not email.isascii() or any(ord(c) < 33 or ord(c) == 127 for c in email):
        return "the email address may only contain printable ASCII characters"
    return None


def find_account(db: DB, *, login: str) -> User | None:
    """The account a login names, by its username (whatever its case) or its email address."""
    login = login.strip()
    return db.scalar(
        select(User).where(
            (func.lower(User.username) == login.lower()) | (User.email == normalise_email(login))
        )
    )


def authenticate(db: DB, *, login: str, password: str) -> User | None:
    """The user whose username or email and password match; same cost whether or not it exists."""
    return _verify(find_account(db, login=login), password)


def _verify(user: User | None, password: str) -> User | None:
    if user is None:
        security.dummy_verify(password)
        return None
    if not security.verify_password(user.password_hash, password):
        return None
    if security.password_needs_rehash(user.password_hash):
        user.password_hash = security.hash_password(password)
    return user


@dataclass(frozen=True)
class LoginThrottle:
    """Where failed logins are counted, and how many each bucket allows (docs/server.md)."""

    limiter: RateLimiter
    per_address: Rate
    per_account_address: Rate


def password_login(
    db: DB, *, login: str, password: str, address: str, throttle: LoginThrottle
) -> User:
    """The account, or Unauthorized (one message for every failure) / RateLimited.

    OWASP's authentication guidance: failures are counted per (account, address) and per
    address, never per account alone, so nobody can lock an owner out from elsewhere; the
    account is resolved first, so its user name and its email share one bucket.
    """
    account = find_account(db, login=login)
    # An unknown name gets a bucket of its own too: answering 429 only for real accounts
    # would tell which names exist.
    who = f"user:{account.id}" if account is not None else f"name:{login.strip().casefold()}"
    buckets = [
        (f"login-fail:ip:{address}", throttle.per_address),
        (f"login-fail:{who}:ip:{address}", throttle.per_account_address),
    ]
    for key, rate in buckets:
        decision = throttle.limiter.peek(key, rate)
        if not decision.allowed:
            raise RateLimited(
                "too many failed logins from this address; "
                f"try again in {decision.retry_after:.0f} s",
                retry_after=decision.retry_after,
            )
    user = _verify(account, password)
    if user is None:
        for key, rate in buckets:
            throttle.limiter.hit(key, rate)
        raise Unauthorized("wrong username, email or password")
    refuse_disabled(user)  # only to whoever knows the password: it tells the account exists
    return user


class AccountDisabled(Forbidden):
    """An administrator disabled the account: it neither logs in nor uses its API tokens."""

    code = "account_disabled"


def refuse_disabled(user: User) -> None:
    """AccountDisabled, with the administrator's reason, if the account is disabled."""
    if user.disabled_at is not None:
        raise AccountDisabled(f"this account is disabled: {user.disabled_reason or 'no reason'}")


def set_password(
    db: DB, user: User, password: str, *, min_score: int = security.DEFAULT_MIN_SCORE
) -> None:
    """Change a password and end every browser session of the account."""
    if found := security.password_problems(
        password, username=user.username, email=user.email, min_score=min_score
    ):
        raise Invalid("the password is too weak", fields={"password": " ".join(found)})
    user.password_hash = security.hash_password(password)
    db.execute(update(Session).where(Session.user_id == user.id).values(expires_at=utcnow()))


# Sessions -----------------------------------------------------------------------------------


def open_session(db: DB, *, user: User, days: int) -> str:
    """A new browser session for `user`; returns the cookie value (stored only hashed)."""
    issued = security.new_secret("session")
    db.add(
        Session(
            user_id=user.id,
            prefix=issued.prefix,
            digest=issued.digest,
            expires_at=utcnow() + timedelta(days=days),
        )
    )
    db.flush()
    return issued.plaintext


def session_for(db: DB, *, cookie: str | None) -> Session | None:
    """The live session a cookie names, or None (unknown, forged or expired)."""
    if not cookie or (parsed := security.parse_secret(cookie, "session")) is None:
        return None
    prefix, digest = parsed
    found = db.scalar(
        select(Session).options(joinedload(Session.user)).where(Session.prefix == prefix)
    )
    if found is None or not security.secrets_equal(found.digest, digest):
        return None
    if found.expires_at <= utcnow() or found.user.disabled_at is not None:
        return None
    return found


def close_session(db: DB, *, session: Session) -> None:
    """Log out: the session is deleted (`session` may come from another database session)."""
    db.delete(db.merge(session))


# API tokens ---------------------------------------------------------------------------------


def create_token(db: DB, *, user: User, name: str) -> tuple[ApiToken, str]:
    """A new named token; the plaintext is returned once and never stored."""
    name = name.strip()
    if not 1 <= len(name) <= 64 or not name.isprintable():
        raise Invalid("bad token name", fields={"name": "1 to 64 printable characters"})
    live = db.scalar(
        select(func.count())
        .select_from(ApiToken)
        .where(ApiToken.user_id == user.id, ApiToken.revoked_at.is_(None))
    )
    if (live or 0) >= MAX_TOKENS_PER_USER:
        raise Conflict(f"at most {MAX_TOKENS_PER_USER} live tokens; revoke one first")
    issued = security.new_secret("token")
    token = ApiToken(user_id=user.id, name=name, prefix=issued.prefix, digest=issued.digest)
    db.add(token)
    db.flush()
    return token, issued.plaintext


def user_for_token(db: DB, *, plaintext: str, now: datetime | None = None) -> User | None:
    """The owner of a live API token, or None (AccountDisabled for a disabled owner's);
    records when the token was last used."""
    if (parsed := security.parse_secret(plaintext, "token")) is None:
        return None
    prefix, digest = parsed
    token = db.scalar(
        select(ApiToken).options(joinedload(ApiToken.user)).where(ApiToken.prefix == prefix)
    )
    if token is None or token.revoked_at is not None:
        return None
    if not security.secrets_equal(token.digest, digest):
        return None
    refuse_disabled(token.user)
    now = now or utcnow()
    # Record use at most once a minute: a CLI polling status must not write on every call.
    if token.last_used_at is None or now - token.last_used_at > timedelta(minutes=1):
        token.last_used_at = now
    return token.user


def list_tokens(db: DB, *, user: User) -> list[ApiToken]:
    """The user's API tokens, newest first, revoked ones included."""
    return list(
        db.scalars(select(ApiToken).where(ApiToken.user_id == user.id).order_by(ApiToken.id.desc()))
    )


def revoke_token(db: DB, *, user: User, token_id: int) -> ApiToken | None:
    """Revoke one of the user's tokens (again is a no-op); None when the user has no such token."""
    token = db.get(ApiToken, token_id)
    if token is None or token.user_id != user.id:
        return None
    if token.revoked_at is None:
        token.revoked_at = utcnow()
    return token


# Administration ------------------------------------------------------------------------------


@dataclass(frozen=True)
class UserRow:
    """An account as the administrators' list shows it."""

    user: User
    submissions: int
    """The participant's own submissions (re-evaluations of them not counted)."""


_OWN_SUBMISSION = Submission.reevaluation_of.is_(None)
"""A participant's own submission: not a re-evaluation of one (docs/server.md, Re-evaluation)."""


def user_row(db: DB, *, user: User) -> UserRow:
    """The account with its submission count."""
    n = db.scalar(
        select(func.count())
        .select_from(Submission)
        .where(Submission.user_id == user.id, _OWN_SUBMISSION)
    )
    return UserRow(user=user, submissions=n or 0)


def list_users(db: DB, *, search: str = "", page: int, per_page: int) -> tuple[list[UserRow], int]:
    """One page of accounts, newest first, whose name or address contains `search` (any
    case), with their submission counts; and how many match."""
    query = select(User)
    if needle := search.strip().lower():
        escaped = needle.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        pattern = f"%{escaped}%"
        query = query.where(
            func.lower(User.username).like(pattern, escape="\\")
            | User.email.like(pattern, escape="\\")
        )
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    counts = (
        select(Submission.user_id, func.count().label("n"))
        .where(_OWN_SUBMISSION)
        .group_by(Submission.user_id)
        .subquery()
    )
    rows = db.execute(
        query.add_columns(func.coalesce(counts.c.n, 0))
        .outerjoin(counts, counts.c.user_id == User.id)
        .order_by(User.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    return [UserRow(user=user, submissions=int(n)) for user, n in rows], total


def get_user(db: DB, *, user_id: int) -> User:
    """The account with this id, or NotFound."""
    user = db.get(User, user_id)
    if user is None:
        raise NotFound(f"no user {user_id}")
    return user


def named_user(db: DB, *, username: str) -> User:
    """The account with this name (any case), or NotFound."""
    user = user_named(db, username=username)
    if user is None:
        raise NotFound(f"no user {username!r}")
    return user


def _not_yourself(user: User, by: User | None, what: str) -> None:
    if by is not None and by.id == user.id:
        raise Forbidden(f"you cannot {what} your own account: ask another administrator")


def disable_user(
    db: DB, *, user: User, by: User | None, reason: str | None, now: datetime | None = None
) -> User:
    """Disable an account (`by` an administrator, None: the command line): it can no longer log
    in or use its tokens, and its browser sessions end. Its unfinished submissions are the
    caller's to cancel (server/console/users.py), from the floor that may."""
    why = audit.reason_of(reason, required=True)
    _not_yourself(user, by, "disable")
    if user.disabled_at is not None:
        raise Conflict(f"{user.username} is disabled already")
    now = now or utcnow()
    user.disabled_at, user.disabled_reason = now, why
    db.execute(update(Session).where(Session.user_id == user.id).values(expires_at=now))
    audit.record(
        db, by=by, action="user.disable", target_kind="user", target_id=user.id, reason=why
    )
    db.flush()
    return user


def enable_user(db: DB, *, user: User, by: User | None, reason: str | None = None) -> User:
    """Let a disabled account log in and use its tokens again."""
    why = audit.reason_of(reason, required=False)
    if user.disabled_at is None:
        raise Conflict(f"{user.username} is not disabled")
    detail = {"disabled_at": user.disabled_at.isoformat(), "disabled_reason": user.disabled_reason}
    user.disabled_at, user.disabled_reason = None, None
    audit.record(
        db,
        by=by,
        action="user.enable",
        target_kind="user",
        target_id=user.id,
        reason=why,
        detail=detail,
    )
    db.flush()
    return user


def mark_verified(db: DB, *, user: User, by: User | None, now: datetime | None = None) -> User:
    """Mark the account's address verified, as following the mailed link would."""
    if user.email_verified_at is not None:
        raise Conflict(f"the address of {user.username} is verified already")
    user.email_verified_at = now or utcnow()
    audit.record(
        db,
        by=by,
        action="user.verify",
        target_kind="user",
        target_id=user.id,
        detail={"email": user.email},
    )
    db.flush()
    return user


def set_admin(db: DB, *, user: User, by: User | None, admin: bool) -> User:
    """Grant (or revoke) an account's administrator rights; never one's own."""
    _not_yourself(user, by, "grant or revoke administrator rights of")
    if user.is_admin == admin:
        already = "an administrator" if admin else "not an administrator"
        raise Conflict(f"{user.username} is {already} already")
    user.is_admin = admin
    audit.record(
        db,
        by=by,
        action="user.grant_admin" if admin else "user.revoke_admin",
        target_kind="user",
        target_id=user.id,
        detail={"old": {"is_admin": not admin}, "new": {"is_admin": admin}},
    )
    db.flush()
    return user
