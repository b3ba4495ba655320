"""Account pages: register, log in and out, and the account page with its API tokens."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.accounts import service as accounts
from server.kit.deps import SESSION_COOKIE, DBDep, Id, client_ip, limit, login_throttle, services
from server.kit.errors import AppError, NotFound, Unauthorized
from server.kit.pages import (
    PostedDep,
    Viewer,
    ViewerDep,
    redirect,
    render,
    safe_next,
    signed_in,
)
from server.models import User

router = APIRouter(include_in_schema=False)

Text = Annotated[str, Form(max_length=1024)]
NextPath = Annotated[str, Form(max_length=2000)]
NOTICES = {"revoked": "The token is revoked: programs using it are refused from now on."}


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
    username: Text = "",
    email: Text = "",
    password: Text = "",
    next: NextPath = "",
) -> Response:
    """Create an account and log in with it."""
    form = {"username": username, "email": email}
    try:
        limit(request, "register")
        user = accounts.register(
            db,
            username=username,
            email=email,
            password=password,
            min_score=services(request).settings.password_min_score,
        )
        db.commit()
    except AppError as exc:
        return _form_error(request, who, "register.html", exc, form=form, next=next)
    return _login_response(request, db, user, next)


@router.get("/login")
def login_form(
    request: Request, who: ViewerDep, next: Annotated[str, Query(max_length=2000)] = ""
) -> Response:
    return render(request, who, "login.html", errors={}, message="", form={}, next=next)


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
        )
    except AppError as exc:
        return _form_error(request, who, "login.html", exc, form=form, next=next)
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
    context = {"new_token": None, "errors": {}, "message": "", "notice": "", **context}
    return render(
        request,
        who,
        "account.html",
        status=status,
        user=user,
        tokens=accounts.list_tokens(db, user=user),
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
