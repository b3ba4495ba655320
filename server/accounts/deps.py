"""Who is asking: the caller of the API (an API token or the session cookie) and the viewer of
a page (the session cookie), as FastAPI dependencies every domain's routes take."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Form, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from server.accounts import service as accounts
from server.kit import security
from server.kit.deps import CSRF_HEADER, SAFE_METHODS, SESSION_COOKIE, DBDep, client_ip, services
from server.kit.errors import Forbidden, Unauthorized
from server.kit.pages import Viewer, check_posted, viewer_for
from server.kit.ratelimit import Rate
from server.models import Session, User


@dataclass(frozen=True)
class Caller:
    user: User | None
    session: Session | None  # set when authenticated by the session cookie


# Declares the API token in the OpenAPI document (Swagger's Authorize button) and reads it. Not
# `auto_error`: the cookie works too, and public routes take anonymous callers.
bearer = HTTPBearer(
    scheme_name="apiToken",
    bearerFormat="mev_...",
    description="An API token from your account page or `manieval login`.",
    auto_error=False,
)
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Security(bearer)]


def caller(request: Request, db: DBDep, credentials: BearerDep) -> Caller:
    """Who is asking: an API token (Authorization: Bearer) or the session cookie.

    Cookie-authenticated API writes must carry the CSRF token in the X-CSRF-Token header (the
    web pages check their form field themselves, `posted` below); token requests need none,
    since a browser never attaches them by itself.
    """
    if request.headers.get("authorization") is not None:
        if credentials is None or not credentials.credentials.strip():
            raise Unauthorized("use 'Authorization: Bearer <token>'")
        user = accounts.user_for_token(db, plaintext=credentials.credentials.strip())
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


def admin_of(who: Caller) -> User:
    """The caller if an administrator (401, 403 otherwise), asked inside a route whose body is
    checked first: a malformed body is a 422 whoever sends it, as on every other route."""
    return require_admin(require_user(who))


def viewer(request: Request, db: DBDep) -> Viewer:
    """The viewer from the session cookie (API tokens are for programs, not pages)."""
    session = accounts.session_for(db, cookie=request.cookies.get(SESSION_COOKIE))
    return viewer_for(request, session)


ViewerDep = Annotated[Viewer, Depends(viewer)]


def error_page_viewer(request: Request) -> Viewer:
    """The viewer of an error page, which has no dependencies: read in a session of its own."""
    with services(request).sessions() as db:
        return viewer_for(
            request, accounts.session_for(db, cookie=request.cookies.get(SESSION_COOKIE))
        )


async def posted(
    request: Request, who: ViewerDep, csrf_token: Annotated[str, Form()] = ""
) -> Viewer:
    """The viewer of a form POST whose CSRF token and fields pass `check_posted`
    (server/kit/pages.py); otherwise 403 (or 422) and nothing is done."""
    await check_posted(request, who, csrf_token)
    return who


PostedDep = Annotated[Viewer, Depends(posted)]


def login_throttle(request: Request) -> accounts.LoginThrottle:
    """Where this server counts failed logins (docs/server.md, Login throttling)."""
    svc = services(request)
    return accounts.LoginThrottle(
        limiter=svc.limiter,
        per_address=Rate.parse(svc.settings.login_failures_per_address),
        per_account_address=Rate.parse(svc.settings.login_failures_per_account_address),
    )


def registration_throttle(request: Request) -> accounts.RegistrationThrottle:
    """Where this server counts registrations from the caller's address (docs/server.md,
    Accounts): accounts at MANIEVAL_REGISTER_RATE, attempts at MANIEVAL_LOGIN_RATE."""
    svc = services(request)
    return accounts.RegistrationThrottle(
        limiter=svc.limiter,
        accounts=svc.settings.rate("register"),
        attempts=svc.settings.rate("login"),
        address=client_ip(request),
    )
