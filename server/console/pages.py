"""The console's pages for challenges: the admin home (`/admin`), a challenge's settings
(`/admin/challenges/{slug}`) and the audit records (`/admin/audit`). Administrators only; the
forms call the challenges' services, as the API does."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import Response
from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server import audit
from server.accounts.deps import PostedDep, ViewerDep
from server.challenges import service as challenges
from server.challenges.tracks import track_name, tracks_of
from server.console.forms import act_and_return
from server.console.overview import overview, phase_status
from server.console.records import challenge_slugs, shown
from server.kit.deps import DBDep, services
from server.kit.errors import AppError, Invalid
from server.kit.pages import Viewer, admin_signed_in, render
from server.models import AuditRecord, utcnow
from server.submissions.reconcile import timeouts_of

router = APIRouter(include_in_schema=False)

LATEST_RECORDS = 10
RECORDS_PER_PAGE = 50
DONE = {
    "settings": "The challenge's settings are saved.",
    "dates": "The phase's dates are saved.",
    "open": "The phase is open.",
    "close": "The phase is closed: later submissions go by its after-close rule.",
    "publish": "The phase's board is public.",
}
SlugText = Annotated[str, Query(max_length=64)]
FormText = Annotated[str, Form(max_length=64)]


@router.get("/admin")
def home(request: Request, who: ViewerDep, db: DBDep) -> Response:
    """Every challenge with its tracks, phases and submissions, and the latest audit records."""
    admin_signed_in(request, who)
    now = utcnow()
    records = audit.records(db, limit=LATEST_RECORDS)
    return render(
        request,
        who,
        "console/home.html",
        groups=overview(db, timeouts=timeouts_of(services(request).settings), now=now),
        records=shown(db, records),
        now=now,
    )


@router.get("/admin/audit")
def audit_records(
    request: Request,
    who: ViewerDep,
    db: DBDep,
    challenge: SlugText = "",
    action: Annotated[str, Query(max_length=64)] = "",
    before: Annotated[int | None, Query(ge=1, le=2**31 - 1)] = None,
) -> Response:
    """The audit records, newest first, of a challenge and an action if chosen; a page ends
    with a link to the records before its last."""
    admin_signed_in(request, who)
    slugs = challenge_slugs(db)
    challenge_id = next((i for i, slug in slugs.items() if slug == challenge), None)
    unknown = bool(challenge) and challenge_id is None
    found = (
        []
        if unknown
        else audit.records(
            db,
            challenge_id=challenge_id,
            action=action or None,
            before_id=before,
            limit=RECORDS_PER_PAGE + 1,
        )
    )
    filters = {k: v for k, v in (("challenge", challenge), ("action", action)) if v}
    older = None
    if len(found) > RECORDS_PER_PAGE:
        found = found[:RECORDS_PER_PAGE]
        older = f"/admin/audit?{urlencode({**filters, 'before': found[-1].id})}"
    actions = sorted(db.scalars(select(AuditRecord.action).distinct()))
    return render(
        request,
        who,
        "console/audit.html",
        records=shown(db, found),
        filters={"challenge": challenge, "action": action},
        challenges=sorted(slugs.values()),
        actions=actions,
        older=older,
        newest=f"/admin/audit?{urlencode(filters)}" if before is not None else None,
    )


# A challenge's settings ------------------------------------------------------------------------


def _settings_page(
    request: Request,
    who: Viewer,
    db: DB,
    slug: str,
    *,
    error: AppError | None = None,
    form: dict[str, str] | None = None,
    error_phase: str = "",
    done: str = "",
) -> Response:
    challenge = challenges.get_challenge(db, slug=slug)
    now = utcnow()
    return render(
        request,
        who,
        "console/challenge.html",
        challenge=challenge,
        tracks=[(track_name(t), t) for t in tracks_of(db, challenge)],
        phases=[(p, phase_status(p, now)) for p in challenge.phases],
        # The form again with its problem: a page that renders is a 200, as the submit form.
        errors=error.fields if error is not None else {},
        message=error.message if error is not None else "",
        form=form or {},
        error_phase=error_phase,
        notice=DONE.get(done, ""),
    )


@router.get("/admin/challenges/{slug}")
def challenge_settings(
    slug: str,
    request: Request,
    who: ViewerDep,
    db: DBDep,
    done: Annotated[str, Query(max_length=20)] = "",
) -> Response:
    """A challenge's quotas, team mode, and each phase's dates, with open, close and publish."""
    admin_signed_in(request, who)
    return _settings_page(request, who, db, slug, done=done)


def _attempt(
    request: Request,
    who: Viewer,
    db: DB,
    slug: str,
    act: Callable[[], object],
    *,
    done: str,
    form: dict[str, str] | None = None,
    error_phase: str = "",
) -> Response:
    """`act_and_return` on the challenge's settings page."""
    return act_and_return(
        db,
        act,
        page=f"/admin/challenges/{slug}",
        done=done,
        refused=lambda exc: _settings_page(
            request, who, db, slug, error=exc, form=form, error_phase=error_phase
        ),
    )


@router.post("/admin/challenges/{slug}/settings")
def save_settings(
    slug: str,
    request: Request,
    who: PostedDep,
    db: DBDep,
    quota_per_day: FormText = "",
    quota_concurrent: FormText = "",
    team_mode: FormText = "",
) -> Response:
    """Save the quotas and the team mode (a change of it recomputes the boards)."""
    admin = admin_signed_in(request, who)
    form = {"quota_per_day": quota_per_day, "quota_concurrent": quota_concurrent}

    def act() -> None:
        challenges.update_challenge(
            db,
            slug=slug,
            by=admin,
            quota_per_day=_whole(quota_per_day),
            quota_concurrent=_whole(quota_concurrent),
            team_mode=team_mode == "on",
        )

    return _attempt(request, who, db, slug, act, done="settings", form=form)


def _whole(text: str) -> int:
    """A number field's value; text that is no whole number reads as 0, which the service
    refuses with the field's rule."""
    try:
        return int(text.strip())
    except ValueError:
        return 0


@router.post("/admin/challenges/{slug}/phases/{phase}/dates")
def save_dates(
    slug: str,
    phase: str,
    request: Request,
    who: PostedDep,
    db: DBDep,
    opens_at: FormText = "",
    closes_at: FormText = "",
) -> Response:
    """Save a phase's dates (UTC; empty: none)."""
    admin = admin_signed_in(request, who)
    form = {"opens_at": opens_at, "closes_at": closes_at}

    def act() -> None:
        opens, closes = _date(form, "opens_at"), _date(form, "closes_at")
        current = challenges.get_phase(challenges.get_challenge(db, slug=slug), phase)
        challenges.update_phase(
            db,
            slug=slug,
            phase=phase,
            by=admin,
            opens_at=_change(opens, current.opens_at),
            closes_at=_change(closes, current.closes_at),
        )

    return _attempt(request, who, db, slug, act, done="dates", form=form, error_phase=phase)


def _date(form: dict[str, str], name: str) -> datetime | None:
    text = form[name].strip()
    if not text:
        return None
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        raise Invalid(
            "the phase's dates are not valid",
            fields={name: "a date and time like 2027-01-31T12:00 (UTC)"},
        ) from None


def _change(sent: datetime | None, stored: datetime | None) -> challenges.DateChange:
    """What the form asks of a date: the page shows dates to the minute, so a date sent back
    as it was shown is left as it is (a closed phase's past close date among them)."""
    if sent is not None and sent.tzinfo is None:
        sent = sent.replace(tzinfo=UTC)
    as_shown = stored.replace(second=0, microsecond=0) if stored is not None else None
    return challenges.KEEP if sent == as_shown else sent


@router.post("/admin/challenges/{slug}/phases/{phase}/open")
def open_now(slug: str, phase: str, request: Request, who: PostedDep, db: DBDep) -> Response:
    """Open the phase now (a closed one opens again, with no close date)."""
    admin = admin_signed_in(request, who)

    def act() -> None:
        challenges.open_phase(db, slug=slug, phase=phase, by=admin)

    return _attempt(request, who, db, slug, act, done="open", error_phase=phase)


@router.post("/admin/challenges/{slug}/phases/{phase}/close")
def close_now(slug: str, phase: str, request: Request, who: PostedDep, db: DBDep) -> Response:
    """Close the phase now: the close an organizer makes anywhere (`close_phase`)."""
    admin = admin_signed_in(request, who)

    def act() -> None:
        challenges.close_phase(db, by=admin, slug=slug, phase=phase)

    return _attempt(request, who, db, slug, act, done="close", error_phase=phase)


@router.post("/admin/challenges/{slug}/phases/{phase}/publish")
def publish(slug: str, phase: str, request: Request, who: PostedDep, db: DBDep) -> Response:
    """Show the phase's hidden board to everyone (`publish_board`)."""
    admin = admin_signed_in(request, who)

    def act() -> None:
        challenges.publish_board(db, by=admin, slug=slug, phase=phase)

    return _attempt(request, who, db, slug, act, done="publish", error_phase=phase)
