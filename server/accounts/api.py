"""The accounts API, ``/api/v1``: register, log in and out, who am I, and API tokens."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from server.accounts import service as accounts
from server.accounts.schemas import (
    LoginIn,
    NewTokenOut,
    RegisterIn,
    SessionOut,
    TokenIn,
    TokenLoginIn,
    TokenOut,
    UserOut,
)
from server.kit import security
from server.kit.deps import (
    SESSION_COOKIE,
    CallerDep,
    DBDep,
    Id,
    UserDep,
    client_ip,
    limit,
    login_throttle,
    services,
)
from server.kit.errors import ERROR_RESPONSES, NotFound, Unauthorized
from server.kit.schemas import Ok
from server.models import ApiToken, User

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES, tags=["accounts"])


def _user_out(user: User) -> UserOut:
    return UserOut(
        id=user.id,
        username=user.username,
        email=user.email,
        is_admin=user.is_admin,
        created_at=user.created_at,
    )


@router.post("/users", status_code=201)
def register(body: RegisterIn, request: Request, db: DBDep) -> UserOut:
    """Create an account. Rate-limited per client address."""
    limit(request, "register")
    user = accounts.register(
        db,
        username=body.username,
        email=body.email,
        password=body.password,
        min_score=services(request).settings.password_min_score,
    )
    db.commit()
    return _user_out(user)


def _password_login(request: Request, db: DBDep, body: LoginIn) -> User:
    """Throttled as docs/server.md says; one message for every failure."""
    limit(request, "login")  # every attempt, per address: bounds the password hashing it costs
    return accounts.password_login(
        db,
        login=body.login,
        password=body.password,
        address=client_ip(request),
        throttle=login_throttle(request),
    )


@router.post("/session")
def login(body: LoginIn, request: Request, response: Response, db: DBDep) -> SessionOut:
    """Log in for the web pages: sets the session cookie and returns the CSRF token."""
    user = _password_login(request, db, body)
    svc = services(request)
    cookie = accounts.open_session(db, user=user, days=svc.settings.session_days)
    db.commit()
    response.set_cookie(
        SESSION_COOKIE,
        cookie,
        max_age=svc.settings.session_days * 86400,
        httponly=True,
        secure=svc.settings.cookie_secure,
        samesite="lax",
        path="/",
    )
    session = accounts.session_for(db, cookie=cookie)
    assert session is not None
    return SessionOut(
        user=_user_out(user), csrf_token=security.csrf_token(session.digest, svc.csrf_key)
    )


@router.delete("/session")
def logout(who: CallerDep, response: Response, db: DBDep) -> Ok:
    if who.session is not None:
        accounts.close_session(db, session=who.session)
        db.commit()
    response.delete_cookie(SESSION_COOKIE, path="/")
    return Ok()


@router.get("/me")
def me(who: CallerDep, request: Request) -> SessionOut:
    if who.user is None:
        raise Unauthorized("log in or send an API token")
    csrf = (
        security.csrf_token(who.session.digest, services(request).csrf_key)
        if who.session is not None
        else ""
    )
    return SessionOut(user=_user_out(who.user), csrf_token=csrf)


def _token_out(token: ApiToken) -> TokenOut:
    return TokenOut(
        id=token.id,
        name=token.name,
        prefix=token.prefix,
        created_at=token.created_at,
        last_used_at=token.last_used_at,
        revoked_at=token.revoked_at,
    )


@router.post("/auth/token", status_code=201)
def token_login(body: TokenLoginIn, request: Request, db: DBDep) -> NewTokenOut:
    """Exchange a username and password for a new named API token (what `manieval login` does)."""
    user = _password_login(request, db, body)
    limit(request, "token", user=user)
    token, plaintext = accounts.create_token(db, user=user, name=body.name)
    db.commit()
    return NewTokenOut(**_token_out(token).model_dump(), token=plaintext)


@router.get("/tokens")
def list_tokens(user: UserDep, db: DBDep) -> list[TokenOut]:
    return [_token_out(t) for t in accounts.list_tokens(db, user=user)]


@router.post("/tokens", status_code=201)
def create_token(body: TokenIn, request: Request, user: UserDep, db: DBDep) -> NewTokenOut:
    """A new named token. Its value is in this response only: it is stored hashed."""
    limit(request, "token", user=user)
    token, plaintext = accounts.create_token(db, user=user, name=body.name)
    db.commit()
    return NewTokenOut(**_token_out(token).model_dump(), token=plaintext)


@router.delete("/tokens/{token_id}")
def revoke_token(token_id: Id, user: UserDep, db: DBDep) -> TokenOut:
    token = accounts.revoke_token(db, user=user, token_id=token_id)
    if token is None:
        raise NotFound(f"no token {token_id}")
    db.commit()
    return _token_out(token)
