"""What every web page shares: templates, the viewer and their form tokens, security headers,
and `install(app, routers)`, which serves the pages of every domain and their static files.
Who is looking (the session cookie's account) is found by server/accounts/deps.py.

The pages are server-rendered Jinja2 templates (`web/templates`) on the domain code: they call
the same services as the API (no HTTP round trip) and are left out of the OpenAPI document,
which describes the API only.

Pages log in with the same session cookie as the API. Every form POST carries a CSRF token:
the session's (as the API's `X-CSRF-Token`) once logged in; before that (login, register) a
token bound to a random `manieval_form` cookie, so that another site cannot log a visitor in
to an account of its choosing either.
"""

from __future__ import annotations

import hashlib
import secrets
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any
from urllib.parse import quote, urlencode, urlsplit

import jinja2
from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from server.kit import security
from server.kit.db import ROOT
from server.kit.deps import SESSION_COOKIE, services
from server.kit.errors import ErrorDetail, Forbidden, Invalid
from server.kit.schemas import text_problem
from server.models import Session, User

WEB_DIR = ROOT / "web"
TEMPLATES_DIR = WEB_DIR / "templates"
STATIC_DIR = WEB_DIR / "static"
FORM_COOKIE = "manieval_form"
# Forms people also send logged out (a mailed link opened in another browser): a visitor's
# token is bound to the form cookie.
ANONYMOUS_FORMS = frozenset(
    {"/login", "/register", "/verify", "/forgot-password", "/reset-password"}
)
"""The only forms a token bound to the form cookie (not to a session) may post."""
# Paths for programs, whose errors stay the API's JSON body.
MACHINE_PATHS = (
    "/api/",
    "/internal/",
    "/registry/",
    "/healthz",
    "/readyz",
    "/metrics",
    "/docs",
    "/redoc",
    "/openapi.json",
)

# Scripts only from our own /static files: no inline script or event handler can run, so
# markup that slipped through escaping could still not execute anything.
CONTENT_SECURITY_POLICY = "; ".join(
    [
        "default-src 'self'",
        "script-src 'self'",
        "style-src 'self'",
        "img-src 'self'",
        "media-src 'self'",
        "connect-src 'self'",
        "object-src 'none'",
        "base-uri 'none'",
        "form-action 'self'",
        "frame-ancestors 'none'",
    ]
)
SECURITY_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "X-Frame-Options": "DENY",
    "Cache-Control": "no-store",
}


def _static_url(name: str) -> str:
    """`/static/NAME?v=<content hash>`: cached forever by browsers, refreshed on change."""
    path = STATIC_DIR / name
    version = hashlib.sha256(path.read_bytes()).hexdigest()[:12] if path.is_file() else "0"
    return f"/static/{quote(name)}?v={version}"


def _datetime(value: datetime | None) -> str:
    return "" if value is None else f"{value:%Y-%m-%d %H:%M} UTC"


def _percent(value: float | None) -> str:
    return "" if value is None else f"{value * 100:.0f}%"


def _environment() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES_DIR),
        autoescape=True,  # every template, whatever its name: user text is always escaped
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["dt"] = _datetime
    env.filters["pct"] = _percent
    env.globals["static"] = _static_url
    env.globals["urlencode"] = urlencode
    return env


templates = _environment()


@dataclass(frozen=True)
class Viewer:
    """Who is looking at a page, and the CSRF token their forms must carry."""

    user: User | None
    session: Session | None
    csrf: str
    new_form_cookie: str | None = None  # set on the response: a fresh anonymous form token

    @property
    def is_admin(self) -> bool:
        return self.user is not None and self.user.is_admin


def _form_digest(nonce: str) -> str:
    return "form:" + hashlib.sha256(nonce.encode("utf-8", "surrogatepass")).hexdigest()


def viewer_for(request: Request, session: Session | None) -> Viewer:
    """The viewer of a page, logged in by `session` (found by server/accounts/deps.py) or not:
    then their forms carry a token bound to the form cookie, made here when missing."""
    key = services(request).csrf_key
    if session is not None:
        return Viewer(
            user=session.user, session=session, csrf=security.csrf_token(session.digest, key)
        )
    nonce = request.cookies.get(FORM_COOKIE, "")
    fresh = None
    if not 32 <= len(nonce) <= 64:
        nonce = fresh = secrets.token_urlsafe(32)
    return Viewer(
        user=None,
        session=None,
        csrf=security.csrf_token(_form_digest(nonce), key),
        new_form_cookie=fresh,
    )


async def check_posted(request: Request, who: Viewer, csrf_token: str) -> None:
    """Pass a form POST whose CSRF token matches the session, or on the forms of
    `ANONYMOUS_FORMS` the form cookie (a form loaded before logging in elsewhere); otherwise 403
    and nothing is done. Every field must be text the server can store (else 422)."""
    key = services(request).csrf_key
    nonce = request.cookies.get(FORM_COOKIE)
    anonymous_form = request.url.path in ANONYMOUS_FORMS
    if (who.session is not None and security.csrf_valid(csrf_token, who.session.digest, key)) or (
        anonymous_form and nonce and security.csrf_valid(csrf_token, _form_digest(nonce), key)
    ):
        await _check_form_text(request)
        return
    raise Forbidden(
        "This form's security token is missing or out of date. "
        "Go back, reload the page and send the form again."
    )


async def _check_form_text(request: Request) -> None:
    # One check for every form, as `server/kit/schemas.py` does for every JSON body. The form is
    # already parsed (FastAPI parses it once, for the route's fields), so this reads no body.
    form = await request.form()
    problems = {
        name: problem
        for name, value in form.multi_items()
        if isinstance(value, str) and (problem := text_problem(value, multiline=True))
    }
    if problems:
        raise Invalid("the form holds characters that cannot be stored", fields=problems)


class LoginRequired(Exception):
    """Raised by pages that need an account: the visitor is sent to the login page."""

    def __init__(self, next_path: str) -> None:
        super().__init__(next_path)
        self.next_path = next_path


def signed_in(request: Request, who: Viewer) -> User:
    """The viewer's account, or a trip to the login page that comes back here (to the home
    page after a form: its address only takes POSTs)."""
    if who.user is None:
        raise LoginRequired(request.url.path if request.method == "GET" else "/")
    return who.user


def admin_signed_in(request: Request, who: Viewer) -> User:
    """The viewer's account if it is an administrator's: else a trip to the login page (nobody
    logged in) or 403."""
    user = signed_in(request, who)
    if not user.is_admin:
        raise Forbidden("admins only")
    return user


def login_redirect(_request: Request, exc: Exception) -> Response:
    assert isinstance(exc, LoginRequired)
    return redirect(f"/login?{urlencode({'next': exc.next_path})}")


def safe_next(path: str | None, default: str = "/") -> str:
    """A local path to go to after logging in; anything else (another site) is ignored."""
    if not path or not path.startswith("/") or path.startswith("//") or "\\" in path:
        return default
    if any(ord(c) <= 0x20 or ord(c) == 0x7F for c in path) or text_problem(path) is not None:
        return default  # browsers drop tabs and newlines: "/\t/evil.example" is "//evil.example"
    if urlsplit(path).netloc:
        return default
    # A header holds Latin-1 only: other characters ("/\u2215/x") go percent-encoded, which
    # keeps the path local (an encoded character is never a slash to a browser).
    return quote(path, safe="/?#&=+%:;@,!$'()*~")


def redirect(url: str) -> Response:
    return Response(status_code=303, headers={"Location": url, "Cache-Control": "no-store"})


def render(
    request: Request, who: Viewer | None, template: str, *, status: int = 200, **context: Any
) -> HTMLResponse:
    """Render a page (autoescaped) with the security headers and, if needed, the form cookie."""
    html = templates.get_template(template).render(
        viewer=who, path=request.url.path, csrf=who.csrf if who else "", **context
    )
    response = HTMLResponse(html, status_code=status, headers=SECURITY_HEADERS)
    if who is not None and who.new_form_cookie is not None:
        response.set_cookie(
            FORM_COOKIE,
            who.new_form_cookie,
            httponly=True,
            secure=services(request).settings.cookie_secure,
            samesite="lax",
            path="/",
        )
    return response


def error_page(
    request: Request, status: int, title: str, detail: ErrorDetail, *, who: Viewer | None = None
) -> HTMLResponse:
    """The HTML twin of the API's error body, for pages, with the navigation of `who`; without
    (the database may be down) the session cookie gives a guess."""
    signed_in = bool(request.cookies.get(SESSION_COOKIE))
    return render(
        request, who, "error.html", status=status, title=title, detail=detail, signed_in=signed_in
    )


def wants_html(request: Request) -> bool:
    """Pages get HTML errors; the API, the worker API, health checks, metrics and /docs keep
    JSON."""
    return not request.url.path.startswith(MACHINE_PATHS)


def install(app: FastAPI, routers: Iterable[APIRouter]) -> None:
    """Serve the pages of `routers` and their static files from `app`."""
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.add_exception_handler(LoginRequired, login_redirect)
    app.state.page_routers = list(routers)  # what the pages serve, for checks over every form
    for router in app.state.page_routers:
        app.include_router(router)
