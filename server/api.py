"""The public API, ``/api/v1``: accounts, tokens, challenges and leaderboards here; submissions in
``server.api_submissions``, included below."""

from __future__ import annotations

import csv
import io
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi import Path as FastAPIPath
from sqlalchemy import func, select
from starlette.concurrency import run_in_threadpool

from server import accounts, api_submissions, security
from server.challenges import get_challenge, get_phase, suite_of
from server.deps import (
    SESSION_COOKIE,
    CallerDep,
    DBDep,
    Id,
    PageNo,
    PerPage,
    Services,
    UserDep,
    limit,
    services,
)
from server.errors import ERROR_RESPONSES, NotFound, Unauthorized
from server.leaderboard import PageKey, Rendered
from server.models import (
    ApiToken,
    Challenge,
    Phase,
    User,
    utcnow,
)
from server.schemas import (
    ChallengeOut,
    ChallengeSummary,
    ConditionOut,
    LeaderboardOut,
    LeaderboardRowOut,
    LoginIn,
    NewTokenOut,
    Ok,
    Page,
    PhaseOut,
    QuotaOut,
    RegisterIn,
    SessionOut,
    TaskOut,
    TokenIn,
    TokenLoginIn,
    TokenOut,
    UserOut,
)
from server.submissions import (
    quota_use,
)

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)


def _user_out(user: User) -> UserOut:
    return UserOut(
        id=user.id,
        username=user.username,
        email=user.email,
        is_admin=user.is_admin,
        created_at=user.created_at,
    )


# Accounts -------------------------------------------------------------------------------------


@router.post("/users", status_code=201, tags=["accounts"])
def register(body: RegisterIn, request: Request, db: DBDep) -> UserOut:
    """Create an account. Rate-limited per client address."""
    limit(request, "register")
    user = accounts.register(db, username=body.username, email=body.email, password=body.password)
    db.commit()
    return _user_out(user)


def _password_login(request: Request, db: DBDep, body: LoginIn) -> User:
    """Rate-limited per address and per account name; one message for every failure."""
    limit(request, "login", key=body.login.strip().lower())
    user = accounts.authenticate(db, body.login, body.password)
    if user is None:
        raise Unauthorized("wrong username, email or password")
    return user


@router.post("/session", tags=["accounts"])
def login(body: LoginIn, request: Request, response: Response, db: DBDep) -> SessionOut:
    """Log in for the web pages: sets the session cookie and returns the CSRF token."""
    user = _password_login(request, db, body)
    svc = services(request)
    cookie = accounts.open_session(db, user, days=svc.settings.session_days)
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
    session = accounts.session_for(db, cookie)
    assert session is not None
    return SessionOut(
        user=_user_out(user), csrf_token=security.csrf_token(session.digest, svc.csrf_key)
    )


@router.delete("/session", tags=["accounts"])
def logout(who: CallerDep, response: Response, db: DBDep) -> Ok:
    if who.session is not None:
        accounts.close_session(db, db.merge(who.session))
        db.commit()
    response.delete_cookie(SESSION_COOKIE, path="/")
    return Ok()


@router.get("/me", tags=["accounts"])
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


@router.post("/auth/token", status_code=201, tags=["accounts"])
def token_login(body: TokenLoginIn, request: Request, db: DBDep) -> NewTokenOut:
    """Exchange a username and password for a new named API token (what `manieval login` does)."""
    user = _password_login(request, db, body)
    limit(request, "token", user=user)
    token, plaintext = accounts.create_token(db, user, body.name)
    db.commit()
    return NewTokenOut(**_token_out(token).model_dump(), token=plaintext)


@router.get("/tokens", tags=["accounts"])
def list_tokens(user: UserDep, db: DBDep) -> list[TokenOut]:
    tokens = db.scalars(
        select(ApiToken).where(ApiToken.user_id == user.id).order_by(ApiToken.id.desc())
    )
    return [_token_out(t) for t in tokens]


@router.post("/tokens", status_code=201, tags=["accounts"])
def create_token(body: TokenIn, request: Request, user: UserDep, db: DBDep) -> NewTokenOut:
    """A new named token. Its value is in this response only: it is stored hashed."""
    limit(request, "token", user=user)
    token, plaintext = accounts.create_token(db, user, body.name)
    db.commit()
    return NewTokenOut(**_token_out(token).model_dump(), token=plaintext)


@router.delete("/tokens/{token_id}", tags=["accounts"])
def revoke_token(token_id: Id, user: UserDep, db: DBDep) -> TokenOut:
    token = accounts.revoke_token(db, user, token_id)
    if token is None:
        raise NotFound(f"no token {token_id}")
    db.commit()
    return _token_out(token)


# Challenges -----------------------------------------------------------------------------------


def _phases(challenge: Challenge) -> list[PhaseOut]:
    suite = suite_of(challenge)
    now = utcnow()
    return [
        PhaseOut(
            name=p.name,
            description=suite.phases[p.name].description if p.name in suite.phases else "",
            public_seeds=p.public_seeds,
            seed_commitment=p.seed_commitment,
            opens_at=p.opens_at,
            closes_at=p.closes_at,
            open=p.is_open(now),
        )
        for p in challenge.phases
    ]


@router.get("/challenges", tags=["challenges"])
def list_challenges(db: DBDep, page: PageNo = 1, per_page: PerPage = 50) -> Page[ChallengeSummary]:
    total = db.scalar(select(func.count()).select_from(Challenge)) or 0
    rows = db.scalars(
        select(Challenge).order_by(Challenge.id).offset((page - 1) * per_page).limit(per_page)
    )
    items = [
        ChallengeSummary(slug=c.slug, title=c.title, description=c.description, phases=_phases(c))
        for c in rows
    ]
    return Page(items=items, page=page, per_page=per_page, total=total)


@router.get("/challenges/{slug}", tags=["challenges"])
def challenge_detail(slug: str, who: CallerDep, db: DBDep) -> ChallengeOut:
    challenge = get_challenge(db, slug)
    suite = suite_of(challenge)
    quota = None
    if who.user is not None:
        use = quota_use(db, who.user, challenge, now=utcnow())
        quota = QuotaOut(**use.__dict__)
    return ChallengeOut(
        slug=challenge.slug,
        title=challenge.title,
        description=challenge.description,
        phases=_phases(challenge),
        suite_hash=challenge.suite_hash,
        tasks=[
            TaskOut(
                env_id=t.env_id,
                episodes=t.episodes,
                max_episode_steps=t.max_episode_steps,
                obs_mode=t.obs_mode,
                control_mode=t.control_mode,
            )
            for t in suite.tasks
        ],
        conditions=[ConditionOut(name=c.name, kind=c.params.kind) for c in suite.conditions],
        quota_per_day=challenge.quota_per_day,
        quota_concurrent=challenge.quota_concurrent,
        my_quota=quota,
    )


@router.get(
    "/challenges/{slug}/leaderboard",
    tags=["challenges"],
    response_model=LeaderboardOut,
    responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}}}},
)
async def leaderboard(
    slug: Annotated[str, FastAPIPath(max_length=64)],
    request: Request,
    phase: Annotated[str, Query(max_length=32)] = "dev",
    page: PageNo = 1,
    per_page: PerPage = 50,
    format: Literal["json", "csv"] = "json",
) -> Response:
    """Best public submission per user, by score (ties: the earlier submission first).

    The most read page of the service: rendered bytes are cached per board version and
    re-validated against the database at most every `MANIEVAL_LEADERBOARD_MAX_AGE` seconds, so
    a hit costs neither a thread nor a query.
    """
    svc = services(request)
    key = (slug, phase, page, per_page, format)
    rendered = svc.leaderboard_pages.fresh(key)
    if rendered is None:
        rendered = await run_in_threadpool(_render_leaderboard, svc, key)
    return Response(rendered.body, media_type=rendered.media_type, headers=rendered.headers)


def _render_leaderboard(svc: Services, key: PageKey) -> Rendered:
    slug, phase, page, per_page, format = key
    with svc.sessions() as db:
        found = db.execute(
            select(Phase.id, Phase.leaderboard_version)
            .join(Challenge, Phase.challenge_id == Challenge.id)
            .where(Challenge.slug == slug, Phase.name == phase)
        ).first()
        if found is None:
            get_phase(get_challenge(db, slug), phase)  # raises the precise 404 / 422
            raise NotFound(f"no phase {phase!r}")  # pragma: no cover - raced with a delete
        phase_id, version = found
        if (same := svc.leaderboard_pages.revalidate(key, version)) is not None:
            return same
        board = svc.leaderboards.page(db, phase_id, page, per_page)
    out = LeaderboardOut(
        challenge=slug,
        phase=phase,
        page=page,
        per_page=per_page,
        total=board.total,
        items=[LeaderboardRowOut(**row.__dict__) for row in board.rows],
    )
    if format == "csv":
        rendered = Rendered(
            version=version,
            body=_leaderboard_csv(out).encode(),
            media_type="text/csv; charset=utf-8",
            headers={"Content-Disposition": f'attachment; filename="{slug}-{phase}.csv"'},
        )
    else:
        rendered = Rendered(
            version=version, body=out.model_dump_json().encode(), media_type="application/json"
        )
    svc.leaderboard_pages.store(key, rendered)
    return rendered


def _leaderboard_csv(board: LeaderboardOut) -> str:
    tasks = sorted({env for row in board.items for env in row.tasks})
    conditions = sorted({c for row in board.items for c in row.conditions})
    buf = io.StringIO()
    writer = csv.writer(buf)
    header = ["rank", "username", "baseline", "score", "submitted_at", "submission_id"]
    header += [f"{t} success" for t in tasks] + [f"{t} ci_low" for t in tasks]
    header += [f"{t} ci_high" for t in tasks] + [f"condition {c}" for c in conditions]
    writer.writerow(header)
    for row in board.items:
        cells: list[object] = [
            row.rank if row.rank is not None else "",
            _csv_safe(row.username),
            row.baseline,
            f"{row.score:.4f}",
            row.submitted_at.isoformat(),
            row.submission_id,
        ]
        for key in ("success_rate", "ci_low", "ci_high"):
            cells += [f"{row.tasks[t][key]:.4f}" if t in row.tasks else "" for t in tasks]
        cells += [f"{row.conditions[c]:.4f}" if c in row.conditions else "" for c in conditions]
        writer.writerow(cells)
    return buf.getvalue()


def _csv_safe(text: str) -> str:
    """Spreadsheets run cells starting with = + - @ as formulas: defuse them."""
    return "'" + text if text[:1] in ("=", "+", "-", "@") else text


router.include_router(api_submissions.router)
