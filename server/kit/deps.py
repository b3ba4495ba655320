"""Request plumbing: the database session, the CSRF header, rate limits. Who is asking is
server/accounts/deps.py's to say."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated, Protocol

from fastapi import Depends, Query, Request
from fastapi import Path as FastAPIPath
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import sessionmaker

from server.kit.errors import RateLimited
from server.kit.ratelimit import RateLimiter
from server.kit.settings import Settings
from server.models import User

SESSION_COOKIE = "manieval_session"
CSRF_HEADER = "X-CSRF-Token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


class Plumbing(Protocol):
    """What every request may use of the app's services: settings, database sessions, the rate
    limiter. `server/services.py` builds the whole set, with each domain's own parts."""

    settings: Settings
    sessions: sessionmaker[DB]
    limiter: RateLimiter

    @property
    def csrf_key(self) -> bytes: ...


def services(request: Request) -> Plumbing:
    found: Plumbing = request.app.state.services
    return found


def get_db(request: Request) -> Iterator[DB]:
    with services(request).sessions() as db:
        yield db


DBDep = Annotated[DB, Depends(get_db)]


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


PageNo = Annotated[int, Query(ge=1, le=100_000)]
Id = Annotated[int, FastAPIPath(ge=1, le=2**31 - 1)]
PerPage = Annotated[int, Query(ge=1, le=200)]
