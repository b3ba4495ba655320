"""The accounts API, ``/api/v1``: register, log in and out, who am I, API tokens, and the
links mailed to verify an address or reset a password (docs/server.md, Accounts and email)."""

from __future__ import annotations

from fastapi import APIRouter, BackgroundTasks, Request, Response

from server.accounts import service as accounts
from server.accounts import verification
from server.accounts.deps import CallerDep, UserDep, login_throttle, registration_throttle
from server.accounts.mail import announce_mail, duration, letters_for, send_after
from server.accounts.schemas import (
    EmailChangeIn,
    LoginIn,
    MessageOut,
    NewTokenOut,
    PasswordResetConfirmIn,
    PasswordResetIn,
    RegisterIn,
    SessionOut,
    TokenIn,
    TokenLoginIn,
    TokenOut,
    UserOut,
    VerifyIn,
)
from server.kit import security
from server.kit.deps import SESSION_COOKIE, DBDep, Id, client_ip, limit, services
from server.kit.errors import ERROR_RESPONSES, Invalid, NotFound, Unauthorized
from server.kit.schemas import Ok
from server.models import ApiToken, User

router = APIRouter(
    prefix="/api/v1", responses=ERROR_RESPONSES, tags=["accounts"], lifespan=announce_mail
)


def _user_out(user: User) -> UserOut:
    return UserOut(
        id=user.id,
        username=user.username,
        email=user.email,
        email_verified=user.email_verified,
        is_admin=user.is_admin,
        created_at=user.created_at,
    )


@router.post("/users", status_code=201)
def register(body: RegisterIn, request: Request, tasks: BackgroundTasks, db: DBDep) -> UserOut:
    """Create an account and mail a link to verify its address. Every problem with the form
    comes in one answer; only created accounts count against the per-address limit."""
    settings = services(request).settings
    user = accounts.register_counted(
        db,
        throttle=registration_throttle(request),
        username=body.username,
        email=body.email,
        password=body.password,
        min_score=settings.password_min_score,
    )
    mail = verification.verification_mail(db, user=user, letters=letters_for(settings, request))
    db.commit()
    send_after(tasks, settings, mail)
    return _user_out(user)


def _password_login(request: Request, db: DBDep, *, login: str, password: str) -> User:
    """Throttled as docs/server.md says; one message for every failure."""
    limit(request, "login")  # every attempt, per address: bounds the password hashing it costs
    return accounts.password_login(
        db,
        login=login,
        password=password,
        address=client_ip(request),
        throttle=login_throttle(request),
    )


@router.post("/session")
def login(body: LoginIn, request: Request, response: Response, db: DBDep) -> SessionOut:
    """Log in for the web pages: sets the session cookie and returns the CSRF token."""
    user = _password_login(request, db, login=body.login, password=body.password)
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
    user = _password_login(request, db, login=body.login, password=body.password)
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


# Links mailed to the account ------------------------------------------------------------------

CHANGE_SENT = (
    "We sent a link to {email}: your account uses that address once you follow it. "
    "Until then it keeps its current one."
)
RESET_SENT = (
    "If an account uses {email}, we sent it a link to choose a new password. "
    "It works once, for {lifetime}."
)


@router.patch("/me", status_code=202)
def change_email(
    body: EmailChangeIn, request: Request, tasks: BackgroundTasks, user: UserDep, db: DBDep
) -> MessageOut:
    """Move the account to another address: it changes once the link mailed there is followed.
    The answer is the same whether or not another account has that address."""
    try:
        _password_login(request, db, login=user.username, password=body.current_password)
    except Unauthorized:
        raise Invalid(
            "the current password is wrong", fields={"current_password": "wrong password"}
        ) from None
    settings = services(request).settings
    limit(request, "mail", user=user, key=accounts.normalise_email(body.email))
    mail = verification.request_email_change(
        db, user=user, new_email=body.email, letters=letters_for(settings, request)
    )
    db.commit()
    send_after(tasks, settings, mail)
    return MessageOut(message=CHANGE_SENT.format(email=accounts.normalise_email(body.email)))


@router.post("/auth/verify")
def verify(body: VerifyIn, db: DBDep) -> MessageOut:
    """Follow a verification link (the token it carries): the address is the account's, verified."""
    user = verification.verify_email(db, token=body.token)
    db.commit()
    return MessageOut(message=f"The address {user.email} is verified.")


@router.post("/auth/verify/resend", status_code=202)
def resend_verification(
    request: Request, tasks: BackgroundTasks, user: UserDep, db: DBDep
) -> MessageOut:
    """Mail a new verification link to the account's address. Rate-limited."""
    if user.email_verified:
        return MessageOut(message=f"The address {user.email} is verified already.")
    limit(request, "mail", user=user, key=user.email)
    settings = services(request).settings
    mail = verification.verification_mail(db, user=user, letters=letters_for(settings, request))
    db.commit()
    send_after(tasks, settings, mail)
    return MessageOut(message=f"We sent a new link to {user.email}.")


@router.post("/auth/password-reset", status_code=202)
def request_password_reset(
    body: PasswordResetIn, request: Request, tasks: BackgroundTasks, db: DBDep
) -> MessageOut:
    """Mail a link to choose a new password to the account using this address, if any: the
    answer is the same either way. Rate-limited per client address and per address asked."""
    email = accounts.normalise_email(body.email)
    limit(request, "mail", key=email)
    settings = services(request).settings
    letters = letters_for(settings, request)
    mail = verification.password_reset_mail(db, email=email, letters=letters)
    db.commit()
    send_after(tasks, settings, mail)
    return MessageOut(message=RESET_SENT.format(email=email, lifetime=duration(letters.reset_for)))


@router.post("/auth/password-reset/confirm")
def confirm_password_reset(body: PasswordResetConfirmIn, request: Request, db: DBDep) -> MessageOut:
    """Set a new password with a reset link's token. The link then stops working, and the
    account is logged out everywhere (API tokens stay valid)."""
    verification.reset_password(
        db,
        token=body.token,
        password=body.password,
        min_score=services(request).settings.password_min_score,
    )
    db.commit()
    return MessageOut(message="Your password is changed: log in with it.")
