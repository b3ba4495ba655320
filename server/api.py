"""The public API, ``/api/v1``: accounts, tokens, challenges, submissions, leaderboards."""

from __future__ import annotations

import csv
import io
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi import Path as FastAPIPath
from sqlalchemy import func, select
from starlette.concurrency import run_in_threadpool

from server import accounts, security
from server.challenges import get_challenge, get_phase, suite_of
from server.deps import (
    SESSION_COOKIE,
    AdminDep,
    CallerDep,
    DBDep,
    Services,
    UserDep,
    limit,
    services,
)
from server.errors import ERROR_RESPONSES, NotFound, Unauthorized
from server.ingest import condition_means, episode_rows, task_rows
from server.leaderboard import PageKey, Rendered
from server.models import (
    ApiToken,
    Challenge,
    Phase,
    Submission,
    Transition,
    User,
    utcnow,
)
from server.schemas import (
    ChallengeOut,
    ChallengeSummary,
    ConditionOut,
    EpisodeOut,
    LeaderboardOut,
    LeaderboardRowOut,
    LoginIn,
    LogsOut,
    NewTokenOut,
    Ok,
    Page,
    PhaseOut,
    QuotaOut,
    RegisterIn,
    SessionOut,
    SubmissionDetail,
    SubmissionOut,
    SubmissionPatch,
    SubmitIn,
    TaskOut,
    TaskResultOut,
    TokenIn,
    TokenLoginIn,
    TokenOut,
    TransitionOut,
    UserOut,
)
from server.submissions import (
    cancel,
    edit,
    get_visible,
    owned_or_admin,
    quota_use,
    rerun,
    submit,
)

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)

PageNo = Annotated[int, Query(ge=1, le=100_000)]
Id = Annotated[int, FastAPIPath(ge=1, le=2**31 - 1)]
PerPage = Annotated[int, Query(ge=1, le=200)]


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


# Submissions ----------------------------------------------------------------------------------


def _submission_out(s: Submission) -> SubmissionOut:
    return SubmissionOut(
        id=s.id,
        username=s.user.username,
        challenge=s.challenge.slug,
        phase=s.phase.name,
        image=s.image,
        pinned_image=s.pinned_image,
        description=s.description,
        public=s.public,
        hidden=s.hidden,
        baseline=s.baseline,
        state=s.state,
        reason=s.reason,
        attempt=s.attempt,
        created_at=s.created_at,
        started_at=s.started_at,
        finished_at=s.finished_at,
        score=s.score,
        progress=s.progress,
    )


@router.post("/submissions", status_code=202, tags=["submissions"])
def create_submission(body: SubmitIn, request: Request, user: UserDep, db: DBDep) -> SubmissionOut:
    """Submit an image: its tag is resolved and pinned to a digest now; the evaluation is queued."""
    limit(request, "submit", user=user)
    svc = services(request)
    challenge = get_challenge(db, body.challenge)
    phase = get_phase(challenge, body.phase)
    submission = submit(
        db,
        user,
        challenge,
        phase,
        image=body.image,
        description=body.description,
        public=body.public,
        resolve=svc.resolve,
    )
    db.commit()
    svc.dispatcher.dispatch()  # after the commit; the periodic sweep retries if this fails
    return _submission_out(submission)


@router.get("/submissions", tags=["submissions"])
def my_submissions(
    user: UserDep,
    db: DBDep,
    challenge: Annotated[str | None, Query(max_length=64)] = None,
    page: PageNo = 1,
    per_page: PerPage = 50,
) -> Page[SubmissionOut]:
    """Your submissions, newest first."""
    query = select(Submission).where(Submission.user_id == user.id)
    if challenge is not None:
        query = query.where(Submission.challenge_id == get_challenge(db, challenge).id)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.scalars(
        query.order_by(Submission.created_at.desc(), Submission.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    )
    return Page(items=[_submission_out(s) for s in rows], page=page, per_page=per_page, total=total)


@router.get("/submissions/{submission_id}", tags=["submissions"])
def submission_detail(submission_id: Id, who: CallerDep, db: DBDep) -> SubmissionDetail:
    s = get_visible(db, submission_id, who.user)
    transitions = db.scalars(
        select(Transition).where(Transition.submission_id == s.id).order_by(Transition.id)
    )
    rows = task_rows(db, s)
    return SubmissionDetail(
        **_submission_out(s).model_dump(),
        transitions=[
            TransitionOut(
                attempt=t.attempt,
                from_state=t.from_state,
                to_state=t.to_state,
                reason=t.reason,
                at=t.at,
            )
            for t in transitions
        ],
        tasks=[
            TaskResultOut(
                condition=r.condition,
                env_id=r.env_id,
                episodes=r.episodes,
                successes=r.successes,
                success_rate=r.success_rate,
                ci_low=r.ci_low,
                ci_high=r.ci_high,
                mean_steps=r.mean_steps,
            )
            for r in rows
        ],
        conditions=condition_means(rows),
    )


def _owned(db: DBDep, submission_id: Id, user: User | None) -> Submission:
    s = db.get(Submission, submission_id)
    if s is None or not owned_or_admin(s, user):
        raise NotFound(f"no submission {submission_id}")
    return s


@router.get("/submissions/{submission_id}/episodes", tags=["submissions"])
def submission_episodes(
    submission_id: Id,
    who: CallerDep,
    db: DBDep,
    page: PageNo = 1,
    per_page: Annotated[int, Query(ge=1, le=1000)] = 200,
) -> Page[EpisodeOut]:
    """Per-episode records (owner and admins). Seeds of secret-seed phases are never shown."""
    s = _owned(db, submission_id, who.user)
    rows, total = episode_rows(db, s, page=page, per_page=per_page)
    show_seed = s.phase.public_seeds
    items = [
        EpisodeOut(
            condition=condition,
            env_id=env_id,
            index=e.index,
            seed=e.seed if show_seed else None,
            success_once=e.success_once,
            success_at_end=e.success_at_end,
            steps=e.steps,
            episode_return=e.episode_return,
            wall_time_s=e.wall_time_s,
            invalid_actions=e.invalid_actions,
            clipped_actions=e.clipped_actions,
            failure=e.failure,
        )
        for e, condition, env_id in rows
    ]
    return Page(items=items, page=page, per_page=per_page, total=total)


@router.get("/submissions/{submission_id}/logs", tags=["submissions"])
def submission_logs(submission_id: Id, who: CallerDep, db: DBDep) -> LogsOut:
    """The tail of the policy's stdout/stderr (owner and admins)."""
    s = _owned(db, submission_id, who.user)
    return LogsOut(submission_id=s.id, attempt=s.attempt, log_tail=s.log_tail)


@router.post("/submissions/{submission_id}/cancel", tags=["submissions"])
def cancel_submission(submission_id: Id, user: UserDep, db: DBDep) -> SubmissionOut:
    s = _owned(db, submission_id, user)
    cancel(db, user, s)
    db.commit()
    return _submission_out(s)


@router.post("/submissions/{submission_id}/rerun", tags=["admin"])
def rerun_submission(
    submission_id: Id, request: Request, admin: AdminDep, db: DBDep
) -> SubmissionOut:
    """Run an ended submission again as a new attempt (admins)."""
    s = _owned(db, submission_id, admin)
    rerun(db, admin, s)
    db.commit()
    services(request).dispatcher.dispatch()
    return _submission_out(s)


@router.patch("/submissions/{submission_id}", tags=["submissions"])
def update_submission(
    submission_id: Id, body: SubmissionPatch, user: UserDep, db: DBDep
) -> SubmissionOut:
    """Owners change visibility and description; admins also hide and flag baselines."""
    s = _owned(db, submission_id, user)
    edit(
        db,
        user,
        s,
        public=body.public,
        hidden=body.hidden,
        baseline=body.baseline,
        description=body.description,
    )
    db.commit()
    return _submission_out(s)
