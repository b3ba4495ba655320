"""Account pages: register, log in and out, the account page with its API tokens and its
address, and the pages mailed links open (verify an address, reset a password)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, BackgroundTasks, Form, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.accounts import service as accounts
from server.accounts import verification
from server.accounts.deps import PostedDep, ViewerDep, login_throttle, registration_throttle
from server.accounts.mail import duration, letters_for, send_after
from server.kit.deps import SESSION_COOKIE, DBDep, Id, client_ip, limit, services
from server.kit.errors import AppError, Invalid, NotFound, Unauthorized
from server.kit.pages import Viewer, redirect, render, safe_next, signed_in
from server.models import User, team_of

router = APIRouter(include_in_schema=False)

Text = Annotated[str, Form(max_length=1024)]
NextPath = Annotated[str, Form(max_length=2000)]
TokenQuery = Annotated[str, Query(max_length=200)]
NOTICES = {
    "revoked": "The token is revoked: programs using it are refused from now on.",
    "sent": "We sent a new link to your address: follow it to verify the address.",
}
LOGIN_NOTICES = {"reset": "Your password is changed: log in with it."}


def _login_response(request: Request, db: DB, user: User, next_path: str) -> Response:
    """Open a browser session for `user` and go on to `next_path`."""
    settings = services(request).settings
    cookie = accounts.open_session(db, user=user, days=settings.session_days)
    db.commit()
    response = redirect(safe_next(next_path, "/account"))
    response.set_cookie(
        SESSION_COOKIE,
        cookie,
        max_age=settings.session_days * 86400,
        httponly=True,
        secure=settings.cookie_secure,
        samesite="lax",
        path="/",
    )
    return response


def _form_error(
    request: Request, who: Viewer, template: str, exc: AppError, **context: Any
) -> Response:
    """The form again with its problems. A page that renders is a 200 whatever the problem
    (a browser logs any other status as an error); the API keeps its 4xx statuses."""
    response = render(request, who, template, errors=exc.fields, message=exc.message, **context)
    response.headers.update(exc.headers())
    return response


@router.get("/register")
def register_form(
    request: Request, who: ViewerDep, next: Annotated[str, Query(max_length=2000)] = ""
) -> Response:
    return render(request, who, "register.html", errors={}, message="", form={}, next=next)


@router.post("/register")
def register(
    request: Request,
    who: PostedDep,
    db: DBDep,
    tasks: BackgroundTasks,
    username: Text = "",
    email: Text = "",
    password: Text = "",
    next: NextPath = "",
) -> Response:
    """Create an account, mail a link to verify its address, and log in with it."""
    form = {"username": username, "email": email}
    settings = services(request).settings
    try:
        user = accounts.register_counted(
            db,
            throttle=registration_throttle(request),
            username=username,
            email=email,
            password=password,
            min_score=settings.password_min_score,
        )
        mail = verification.verification_mail(db, user=user, letters=letters_for(settings, request))
        db.commit()
    except AppError as exc:
        db.rollback()
        return _form_error(request, who, "register.html", exc, form=form, next=next)
    send_after(tasks, settings, mail)
    return _login_response(request, db, user, next)


@router.get("/login")
def login_form(
    request: Request,
    who: ViewerDep,
    next: Annotated[str, Query(max_length=2000)] = "",
    done: Annotated[str, Query(max_length=20)] = "",
) -> Response:
    notice = LOGIN_NOTICES.get(done, "")
    return render(
        request, who, "login.html", errors={}, message="", form={}, next=next, notice=notice
    )


@router.post("/login")
def login(
    request: Request,
    who: PostedDep,
    db: DBDep,
    login: Text = "",
    password: Text = "",
    next: NextPath = "",
) -> Response:
    """Log in by username or email: one message for every failure, as the API."""
    form = {"login": login}
    try:
        limit(request, "login")  # every attempt, per address: bounds the hashing it costs
        user = accounts.password_login(
            db,
            login=login,
            password=password,
            address=client_ip(request),
            throttle=login_throttle(request),
        )
    except Unauthorized:
        return render(
            request,
            who,
            "login.html",
            errors={},
            message="Wrong username, email or password.",
            form=form,
            next=next,
            notice="",
        )
    except AppError as exc:
        return _form_error(request, who, "login.html", exc, form=form, next=next, notice="")
    return _login_response(request, db, user, next)


@router.get("/logout")
def logout_form(request: Request, who: ViewerDep) -> Response:
    """Ask before logging out: a link cannot log anyone out (that takes the form's POST)."""
    return render(request, who, "logout.html")


@router.post("/logout")
def logout(who: PostedDep, db: DBDep) -> Response:
    if who.session is not None:
        accounts.close_session(db, session=who.session)
        db.commit()
    response = redirect("/")
    response.delete_cookie(SESSION_COOKIE, path="/")
    return response


def _account(
    request: Request, who: Viewer, db: DB, *, status: int = 200, **context: object
) -> Response:
    user = signed_in(request, who)
    context = {
        "new_token": None,
        "errors": {},
        "message": "",
        "notice": "",
        "email_form": {},
        **context,
    }
    return render(
        request,
        who,
        "account.html",
        status=status,
        user=user,
        tokens=accounts.list_tokens(db, user=user),
        team=team_of(db, user_id=user.id),
        **context,
    )


@router.get("/account")
def account(
    request: Request,
    who: ViewerDep,
    db: DBDep,
    done: Annotated[str, Query(max_length=20)] = "",
) -> Response:
    """The account and its API tokens (their values are never shown again)."""
    return _account(request, who, db, notice=NOTICES.get(done, ""))


@router.get("/account/tokens")
def tokens_page() -> Response:
    """The tokens' form's address, opened as a page (a reload, a bookmark): the account page,
    where they are listed. A new token's value is never shown again."""
    return redirect("/account#tokens")


@router.post("/account/tokens")
def create_token(request: Request, who: PostedDep, db: DBDep, name: Text = "") -> Response:
    """A new API token, shown on this response only: it is stored hashed."""
    user = signed_in(request, who)
    try:
        limit(request, "token", user=user)
        token, plaintext = accounts.create_token(db, user=user, name=name)
        db.commit()
    except AppError as exc:
        errors = exc.fields or {"name": exc.message}
        return _account(request, who, db, errors=errors, message=exc.message)  # a page: 200
    return _account(request, who, db, status=201, new_token=(token, plaintext))


@router.post("/account/tokens/{token_id}/revoke")
def revoke_token(request: Request, token_id: Id, who: PostedDep, db: DBDep) -> Response:
    user = signed_in(request, who)
    if accounts.revoke_token(db, user=user, token_id=token_id) is None:
        raise NotFound(f"no token {token_id}")
    db.commit()
    return redirect("/account?done=revoked#tokens")


# The address, and the pages mailed links open -------------------------------------------------


@router.post("/account/email")
def change_email(
    request: Request,
    who: PostedDep,
    db: DBDep,
    tasks: BackgroundTasks,
    email: Text = "",
    current_password: Text = "",
) -> Response:
    """Mail a link to a new address; the account moves there once it is followed."""
    user = signed_in(request, who)
    settings = services(request).settings
    try:
        limit(request, "login")  # as any password check: bounds the hashing it costs
        try:
            accounts.password_login(
                db,
                login=user.username,
                password=current_password,
                address=client_ip(request),
                throttle=login_throttle(request),
            )
        except Unauthorized:
            raise Invalid(
                "The current password is wrong.", fields={"current_password": "Wrong password."}
            ) from None
        limit(request, "mail", user=user, key=accounts.normalise_email(email))
        mail = verification.request_email_change(
            db, user=user, new_email=email, letters=letters_for(settings, request)
        )
        db.commit()
    except AppError as exc:
        db.rollback()
        return _account(
            request, who, db, errors=exc.fields, message=exc.message, email_form={"email": email}
        )
    send_after(tasks, settings, mail)
    notice = (
        f"We sent a link to {accounts.normalise_email(email)}: your account uses that address "
        "once you follow it, and keeps its current one until then."
    )
    return _account(request, who, db, notice=notice)


@router.post("/account/verify")
def resend_verification(
    request: Request, who: PostedDep, db: DBDep, tasks: BackgroundTasks
) -> Response:
    """A new link to verify the account's address (the banner's button)."""
    user = signed_in(request, who)
    settings = services(request).settings
    try:
        limit(request, "mail", user=user, key=user.email)
        mail = verification.verification_mail(db, user=user, letters=letters_for(settings, request))
        db.commit()
    except AppError as exc:
        return _account(request, who, db, message=exc.message)
    send_after(tasks, settings, mail)
    return redirect("/account?done=sent")


@router.get("/verify")
def verify_form(request: Request, who: ViewerDep, token: TokenQuery = "") -> Response:
    """A mailed verification link opens this page, whose button confirms: mail scanners
    fetch links, and a GET must not use the token up."""
    return render(request, who, "verify.html", token=token, verified=None, message="")


@router.post("/verify")
def verify(request: Request, who: PostedDep, db: DBDep, token: Text = "") -> Response:
    try:
        user = verification.verify_email(db, token=token)
        db.commit()
    except AppError as exc:
        return render(request, who, "verify.html", token="", verified=None, message=exc.message)
    return render(request, who, "verify.html", token="", verified=user.email, message="")


@router.get("/forgot-password")
def forgot_password_form(request: Request, who: ViewerDep) -> Response:
    return render(request, who, "forgot_password.html", errors={}, message="", form={}, sent="")


@router.post("/forgot-password")
def forgot_password(
    request: Request, who: PostedDep, db: DBDep, tasks: BackgroundTasks, email: Text = ""
) -> Response:
    """Mail a reset link to the account using `email`, if any: the page is the same either
    way."""
    settings = services(request).settings
    form = {"email": email}
    letters = letters_for(settings, request)
    try:
        limit(request, "mail", key=accounts.normalise_email(email))
        mail = verification.password_reset_mail(db, email=email, letters=letters)
        db.commit()
    except AppError as exc:
        return _form_error(request, who, "forgot_password.html", exc, form=form, sent="")
    send_after(tasks, settings, mail)
    return render(
        request,
        who,
        "forgot_password.html",
        errors={},
        message="",
        form=form,
        sent=accounts.normalise_email(email),
        lifetime=duration(letters.reset_for),
    )


@router.get("/reset-password")
def reset_password_form(
    request: Request, who: ViewerDep, db: DBDep, token: TokenQuery = ""
) -> Response:
    """A mailed reset link opens this form; looking does not use the link up."""
    works = verification.reset_link_works(db, token=token)
    return render(
        request,
        who,
        "reset_password.html",
        token=token if works else "",
        errors={},
        message="" if works else verification.BAD_LINK,
    )


@router.post("/reset-password")
def reset_password(
    request: Request, who: PostedDep, db: DBDep, token: Text = "", password: Text = ""
) -> Response:
    """Set the new password, then log in with it (every session was ended)."""
    try:
        verification.reset_password(
            db,
            token=token,
            password=password,
            min_score=services(request).settings.password_min_score,
        )
        db.commit()
    except AppError as exc:
        db.rollback()
        works = verification.reset_link_works(db, token=token)
        return _form_error(request, who, "reset_password.html", exc, token=token if works else "")
    response = redirect("/login?done=reset")
    response.delete_cookie(SESSION_COOKIE, path="/")
    return response
