"""Request plumbing: the database session, who is asking, CSRF, rate limits."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Query, Request
from fastapi import Path as FastAPIPath
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import sessionmaker

from server.accounts import service as accounts
from server.kit import security
from server.kit.errors import Forbidden, RateLimited, Unauthorized
from server.kit.ratelimit import Rate, RateLimiter
from server.kit.settings import Settings
from server.leaderboard.rendered import BoardPages
from server.leaderboard.snapshot import Snapshots
from server.models import Session, User
from server.submissions.outbox import Dispatcher
from server.submissions.service import Resolver

SESSION_COOKIE = "manieval_session"
CSRF_HEADER = "X-CSRF-Token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


@dataclass
class Services:
    settings: Settings
    sessions: sessionmaker[DB]
    limiter: RateLimiter
    resolve: Resolver
    dispatcher: Dispatcher
    board_pages: BoardPages = field(default_factory=BoardPages)
    """Rendered leaderboard page contents (server/leaderboard/pages.py)."""
    boards: Snapshots = field(init=False)
    """Whole boards per phase for the leaderboard API and pages (server/leaderboard/snapshot.py)."""

    def __post_init__(self) -> None:
        self.boards = Snapshots(self.settings.leaderboard_max_age)

    @property
    def csrf_key(self) -> bytes:
        return self.settings.secret("secret_key").encode()


def services(request: Request) -> Services:
    found: Services = request.app.state.services
    return found


def get_db(request: Request) -> Iterator[DB]:
    with services(request).sessions() as db:
        yield db


@dataclass(frozen=True)
class Caller:
    user: User | None
    session: Session | None  # set when authenticated by the session cookie


def caller(request: Request, db: Annotated[DB, Depends(get_db)]) -> Caller:
    """Who is asking: an API token (Authorization: Bearer) or the session cookie.

    Cookie-authenticated API writes must carry the CSRF token in the X-CSRF-Token header (the
    web pages check their form field themselves, server/kit/pages.py); token requests need
    none, since a browser never attaches them by itself.
    """
    header = request.headers.get("authorization")
    if header is not None:
        scheme, _, value = header.partition(" ")
        if scheme.lower() != "bearer" or not value.strip():
            raise Unauthorized("use 'Authorization: Bearer <token>'")
        user = accounts.user_for_token(db, plaintext=value.strip())
        if user is None:
            raise Unauthorized("the API token is invalid or revoked")
        db.commit()  # last_used_at
        return Caller(user=user, session=None)
    session = accounts.session_for(db, cookie=request.cookies.get(SESSION_COOKIE))
    if session is None:
        return Caller(user=None, session=None)
    if request.method not in SAFE_METHODS:
        token = request.headers.get(CSRF_HEADER)
        if not security.csrf_valid(token, session.digest, services(request).csrf_key):
            raise Forbidden(f"missing or wrong CSRF token (send the {CSRF_HEADER} header)")
    return Caller(user=session.user, session=session)


CallerDep = Annotated[Caller, Depends(caller)]
DBDep = Annotated[DB, Depends(get_db)]


def require_user(who: CallerDep) -> User:
    if who.user is None:
        raise Unauthorized("log in or send an API token")
    return who.user


def require_admin(user: Annotated[User, Depends(require_user)]) -> User:
    if not user.is_admin:
        raise Forbidden("admins only")
    return user


UserDep = Annotated[User, Depends(require_user)]
AdminDep = Annotated[User, Depends(require_admin)]


def client_ip(request: Request) -> str:
    return request.client.host if request.client else "unknown"


def limit(request: Request, action: str, *, user: User | None = None, key: str = "") -> None:
    """Apply the action's rate per client IP and per user (and per extra key, e.g. a login)."""
    svc = services(request)
    rate = svc.settings.rate(action)  # type: ignore[arg-type]
    keys = [f"{action}:ip:{client_ip(request)}"]
    if user is not None:
        keys.append(f"{action}:user:{user.id}")
    if key:
        keys.append(f"{action}:key:{key}")
    for k in keys:
        decision = svc.limiter.hit(k, rate)
        if not decision.allowed:
            raise RateLimited(
                f"too many {action} requests; try again in {decision.retry_after:.0f} s",
                retry_after=decision.retry_after,
            )


def login_throttle(request: Request) -> accounts.LoginThrottle:
    """Where this server counts failed logins (docs/server.md, Login throttling)."""
    svc = services(request)
    return accounts.LoginThrottle(
        limiter=svc.limiter,
        per_address=Rate.parse(svc.settings.login_failures_per_address),
        per_account_address=Rate.parse(svc.settings.login_failures_per_account_address),
    )


PageNo = Annotated[int, Query(ge=1, le=100_000)]
Id = Annotated[int, FastAPIPath(ge=1, le=2**31 - 1)]
PerPage = Annotated[int, Query(ge=1, le=200)]
