"""The submit form, "my submissions", and the administrators' list of every submission."""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session as DB

from server.accounts.deps import PostedDep, ViewerDep
from server.accounts.service import user_named
from server.challenges.quota import quota_use
from server.challenges.service import all_challenges, get_challenge, get_phase, policy_refusal
from server.challenges.tracks import get_track, tracks_of
from server.downloads.artifacts import TEMPLATE_DIR, TEMPLATE_FILE
from server.kit.deps import DBDep, limit
from server.kit.errors import AppError, Invalid
from server.kit.pages import Viewer, admin_signed_in, redirect, render, signed_in
from server.kit.settings import Settings
from server.models import Challenge, State, Submission, User, utcnow
from server.registry.own import plain_http
from server.registry.published import LOCAL_POLICY_BASE, policy_base
from server.registry.tokens import namespace_for
from server.submissions.deps import services
from server.submissions.method import Method
from server.submissions.service import images_refused, list_submissions, submit

router = APIRouter(include_in_schema=False)

MAX_IMAGE_LENGTH = 512  # as the API's SubmitIn
DEFAULT_CLI_SERVER = "http://127.0.0.1:8000"  # what `manieval` reaches without --server
PER_PAGE = 50
PUBLISHED_BASE_TTL_S = 60.0  # how long a page trusts what the registry said of the base
PageNo = Annotated[int, Query(ge=1, le=100_000)]


def _form(
    request: Request,
    who: Viewer,
    db: DB,
    challenge: Challenge,
    *,
    form: dict[str, str],
    error: AppError | None = None,
) -> Response:
    user = signed_in(request, who)
    resets_at = None
    if error is not None and isinstance(stamp := error.extra.get("resets_at"), str):
        resets_at = datetime.fromisoformat(stamp)
    response = render(
        request,
        who,
        "submit.html",
        # The form again with its problem: a page that renders is a 200 (a browser logs any
        # 4xx as an error); the API keeps its statuses.
        challenge=challenge,
        now=utcnow(),
        quota=quota_use(db, user=user, challenge=challenge, now=utcnow()),
        form=form,
        errors=error.fields if error is not None else {},
        message=error.message if error is not None else "",
        resets_at=resets_at,
        local_policies=services(request).settings.allow_local_policies,
        push=push_commands(request, user=user, challenge=challenge),
        images_refused=images_refused(services(request).resolve),
        gpus_refused=policy_refusal(challenge, policy_gpus=services(request).settings.policy_gpus),
        tracks=tracks_of(db, challenge),
    )
    if error is not None:
        response.headers.update(error.headers())
    return response


@dataclass(frozen=True)
class PushCommands:
    """The commands that take this user's policy into the service's registry, filled in."""

    registry: str
    namespace: str
    login: str
    build: list[str]
    push: str
    engine_login: str
    engine_push: str
    example: str


def push_commands(request: Request, *, user: User, challenge: Challenge) -> PushCommands | None:
    """None when the service runs no registry of its own."""
    settings = services(request).settings
    domain = settings.registry_domain
    if domain is None:
        return None
    namespace = namespace_for(user.username) or user.username
    server = server_flag(request)
    tls = _tls_flag(settings, domain)
    tagged = f"{domain}/{namespace}/my-policy:v1"
    fetch, build = template_commands(request, published=published_base(request))
    return PushCommands(
        registry=domain,
        namespace=namespace,
        login=f"manieval login -u {user.username}{server}",
        build=[*fetch, *build],
        push=f"manieval push my-policy:v1 --challenge {challenge.slug} --wait{server}",
        engine_login=f"podman login{tls} -u {user.username} {domain}",
        engine_push=f"podman push{tls} my-policy:v1 {tagged}",
        example=tagged,
    )


def server_flag(request: Request) -> str:
    """` --server URL` for this service, or nothing where `manieval` reaches it by default."""
    base = str(request.base_url).rstrip("/")
    return "" if base == DEFAULT_CLI_SERVER else f" --server {base}"


def template_commands(request: Request, *, published: str | None) -> tuple[list[str], list[str]]:
    """Download the policy template (the SDK inside) from this service, and build its image:
    on the `published` base (:func:`published_base`), pulled with the `manieval login` of the
    steps before, else on a base built from the template's own base/Dockerfile."""
    base = str(request.base_url).rstrip("/")
    fetch = [
        f"curl -fsSLO {base}/downloads/{TEMPLATE_FILE}",
        f"tar xzf {TEMPLATE_FILE}  # unpacks {TEMPLATE_DIR}/, with the SDK beside its Dockerfile",
    ]
    settings = services(request).settings
    if published is not None and settings.registry_domain is not None:
        tls = _tls_flag(settings, settings.registry_domain)
        build = [f"podman build{tls} --build-arg BASE={published} -t my-policy:v1 {TEMPLATE_DIR}"]
    else:
        build = [
            f"podman build -t {LOCAL_POLICY_BASE} {TEMPLATE_DIR}/base  # the base, once",
            f"podman build -t my-policy:v1 {TEMPLATE_DIR}",
        ]
    return fetch, build


def published_base(request: Request) -> str | None:
    """The policy base on this service's registry, pinned by digest, or None when the service
    runs no registry or its registry does not have it (server/registry/published.py). Asked
    of the registry at most once a minute per app: pages never wait on it more often."""
    domain = services(request).settings.registry_domain
    if domain is None:
        return None
    now = time.monotonic()
    known: tuple[float, str | None] | None = getattr(request.app.state, "published_base", None)
    if known is not None and now < known[0]:
        return known[1]
    try:
        found: str | None = services(request).resolve(policy_base(domain)).pinned
    except AppError:  # not published, or the registry is down: the page says how to build it
        found = None
    request.app.state.published_base = (now + PUBLISHED_BASE_TTL_S, found)
    return found


def _tls_flag(settings: Settings, domain: str) -> str:
    """Podman speaks plain HTTP to a registry only when told."""
    return " --tls-verify=false" if plain_http(settings, domain) else ""


@router.get("/challenges/{slug}/submit")
def submit_form(
    slug: str,
    request: Request,
    who: ViewerDep,
    db: DBDep,
    phase: Annotated[str, Query(max_length=32)] = "",
) -> Response:
    signed_in(request, who)
    challenge = get_challenge(db, slug=slug)
    default = {"phase": phase, "image": "", "description": "", "visibility": "public", "track": ""}
    default |= {"method": "", "paper_url": "", "code_url": ""}
    return _form(request, who, db, challenge, form=default)


FormText = Annotated[str, Form(max_length=4000)]


@router.post("/challenges/{slug}/submit")
def submit_post(
    slug: str,
    request: Request,
    who: PostedDep,
    db: DBDep,
    phase: FormText = "",
    image: FormText = "",
    description: FormText = "",
    method: FormText = "",
    paper_url: FormText = "",
    code_url: FormText = "",
    visibility: FormText = "public",
    track: FormText = "",
) -> Response:
    """Accept the submission and go to its page, or show the server's errors by the fields."""
    user = signed_in(request, who)
    challenge = get_challenge(db, slug=slug)
    image = image.strip()
    form = {"phase": phase, "image": image, "description": description, "visibility": visibility}
    form["track"] = track
    form |= {"method": method, "paper_url": paper_url, "code_url": code_url}
    svc = services(request)
    try:
        limit(request, "submit", user=user)
        if not image:
            raise Invalid("enter an image reference", fields={"image": "Enter an image reference."})
        if len(image) > MAX_IMAGE_LENGTH:
            raise Invalid(
                "image reference too long",
                fields={"image": f"At most {MAX_IMAGE_LENGTH} characters."},
            )
        chosen = get_track(db, challenge, track or None)
        submission = submit(
            db,
            user=user,
            challenge=chosen,
            phase=get_phase(chosen, phase),
            image=image,
            description=description,
            public=visibility != "private",
            method=Method(name=method, paper_url=paper_url, code_url=code_url),
            resolve=svc.resolve,
            require_verified_email=svc.settings.email_verification_required,
            policy_gpus=svc.settings.policy_gpus,
        )
        db.commit()
    except AppError as exc:
        db.rollback()
        challenge = get_challenge(db, slug=slug)  # the rollback expired it, and its phases
        return _form(request, who, db, challenge, form=form, error=exc)
    svc.dispatcher.dispatch()  # after the commit; the periodic sweep retries if this fails
    return redirect(f"/submissions/{submission.id}")


@router.get("/submissions")
def my_submissions(request: Request, who: ViewerDep, db: DBDep, page: PageNo = 1) -> Response:
    """The viewer's submissions, newest first."""
    user = signed_in(request, who)
    rows, total = list_submissions(db, user=user, page=page, per_page=PER_PAGE)
    return render(
        request,
        who,
        "submissions.html",
        title="My submissions",
        rows=rows,
        total=total,
        page=page,
        pages=max(1, -(-total // PER_PAGE)),
        pager_base="/submissions?",
        filters=None,
        show_owner=False,
    )


Filter = Annotated[str, Query(max_length=64)]


@router.get("/admin/submissions")
def all_submissions(
    request: Request,
    who: ViewerDep,
    db: DBDep,
    page: PageNo = 1,
    state: Annotated[str, Query(max_length=16)] = "",
    user: Filter = "",
    challenge: Filter = "",
    phase: Filter = "",
) -> Response:
    """Every submission, for administrators, by owner, challenge, phase and state (any of
    them together, kept in the address): where re-run, hide and baseline are one click."""
    admin_signed_in(request, who)
    filters = {"user": user.strip(), "challenge": challenge, "phase": phase, "state": state}
    known = all_challenges(db)
    chosen = next((c for c in known if c.slug == challenge), None)
    owner = user_named(db, username=filters["user"]) if filters["user"] else None
    unknown = [
        f"no user named {filters['user']!r}" if filters["user"] and owner is None else "",
        f"no challenge {challenge!r}" if challenge and chosen is None else "",
    ]
    shown = State(state) if state in {s.value for s in State} else None
    rows: list[Submission] = []
    total = 0
    if not any(unknown):
        rows, total = list_submissions(
            db,
            user=owner,
            challenge=chosen,
            phase=phase or None,
            state=shown,
            page=page,
            per_page=PER_PAGE,
        )
    kept = {name: value for name, value in filters.items() if value}
    return render(
        request,
        who,
        "submissions.html",
        title="All submissions",
        rows=rows,
        total=total,
        page=page,
        pages=max(1, -(-total // PER_PAGE)),
        pager_base="/admin/submissions?" + (urlencode(kept) + "&" if kept else ""),
        filters=filters,
        unknown="; ".join(u for u in unknown if u),
        challenges=[c.slug for c in known],
        phases=sorted({p.name for c in known for p in c.phases}),
        states=[s.value for s in State],
        show_owner=True,
    )
