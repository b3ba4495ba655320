"""The challenges API, ``/api/v1/challenges``: the list, and one challenge with its rules."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter
from fastapi import Path as FastAPIPath

from server.accounts.deps import AdminDep, Caller, CallerDep, admin_of
from server.challenges import service
from server.challenges.quota import quota_use
from server.challenges.schemas import (
    ChallengeOut,
    ChallengeSettingsIn,
    ChallengeSummary,
    ConditionOut,
    PhaseDatesIn,
    PhaseOut,
    QuotaOut,
    TaskOut,
    TrackOut,
    VerificationOut,
)
from server.challenges.service import get_challenge, suite_of
from server.challenges.tracks import head_of, track_name, tracks_of
from server.challenges.verification import stored_verification
from server.kit.deps import DBDep, PageNo, PerPage
from server.kit.errors import ERROR_RESPONSES
from server.kit.schemas import SLUG_PATTERN, Page
from server.models import Challenge, utcnow

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES, tags=["challenges"])


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
            counts=p.counts,  # type: ignore[arg-type]  # the suite's Literal, stored as text
            final_choice=p.final_choice,
            after_close=p.after_close,  # type: ignore[arg-type]
            board=p.board,  # type: ignore[arg-type]
            published_at=p.published_at,
        )
        for p in challenge.phases
    ]


@router.get("/challenges")
def list_challenges(db: DBDep, page: PageNo = 1, per_page: PerPage = 50) -> Page[ChallengeSummary]:
    rows, total = service.list_challenges(db, page=page, per_page=per_page)
    items = [
        ChallengeSummary(slug=c.slug, title=c.title, description=c.description, phases=_phases(c))
        for c in rows
    ]
    return Page(items=items, page=page, per_page=per_page, total=total)


@router.get("/challenges/{slug}")
def challenge_detail(
    slug: Annotated[str, FastAPIPath(max_length=64, pattern=SLUG_PATTERN)],
    who: CallerDep,
    db: DBDep,
) -> ChallengeOut:
    challenge = get_challenge(db, slug=slug)
    suite = suite_of(challenge)
    group = tracks_of(db, challenge)
    quota = None
    if who.user is not None:
        use = quota_use(db, user=who.user, challenge=challenge, now=utcnow())
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
        team_mode=challenge.team_mode,
        my_quota=quota,
        verification=_verification(challenge),
        track=track_name(challenge),
        tracks=[TrackOut(name=track_name(t), slug=t.slug, title=t.title) for t in group],
        quota_shared=head_of(db, challenge).quota_shared,
        evaluator_image=challenge.evaluator_image if who.user and who.user.is_admin else None,
    )


SlugPath = Annotated[str, FastAPIPath(max_length=64, pattern=SLUG_PATTERN)]
PhasePath = Annotated[str, FastAPIPath(max_length=32)]


@router.post("/challenges/{slug}/phases/{phase}/close", tags=["admin"])
def close_phase(slug: SlugPath, phase: PhasePath, admin: AdminDep, db: DBDep) -> ChallengeOut:
    """Close the phase now (admins): later submissions go by its `after_close` rule."""
    service.close_phase(db, by=admin, slug=slug, phase=phase)
    db.commit()
    return challenge_detail(slug, Caller(user=admin, session=None), db)


@router.post("/challenges/{slug}/phases/{phase}/publish", tags=["admin"])
def publish_board(slug: SlugPath, phase: PhasePath, admin: AdminDep, db: DBDep) -> ChallengeOut:
    """Show the phase's hidden board to everyone (admins)."""
    service.publish_board(db, by=admin, slug=slug, phase=phase)
    db.commit()
    return challenge_detail(slug, Caller(user=admin, session=None), db)


@router.patch("/challenges/{slug}", tags=["admin"])
def update_challenge(
    slug: SlugPath, body: ChallengeSettingsIn, who: CallerDep, db: DBDep
) -> ChallengeOut:
    """Change the challenge's quotas or team mode (admins); audited with old and new values."""
    admin = admin_of(who)
    service.update_challenge(
        db,
        slug=slug,
        by=admin,
        quota_per_day=body.quota_per_day,
        quota_concurrent=body.quota_concurrent,
        team_mode=body.team_mode,
    )
    db.commit()
    return challenge_detail(slug, Caller(user=admin, session=None), db)


@router.patch("/challenges/{slug}/phases/{phase}", tags=["admin"])
def update_phase(
    slug: SlugPath, phase: PhasePath, body: PhaseDatesIn, who: CallerDep, db: DBDep
) -> ChallengeOut:
    """Move the phase's opening or closing date (admins); null removes it."""
    admin = admin_of(who)
    given = body.model_fields_set
    service.update_phase(
        db,
        slug=slug,
        phase=phase,
        by=admin,
        opens_at=body.opens_at if "opens_at" in given else service.KEEP,
        closes_at=body.closes_at if "closes_at" in given else service.KEEP,
    )
    db.commit()
    return challenge_detail(slug, Caller(user=admin, session=None), db)


@router.post("/challenges/{slug}/phases/{phase}/open", tags=["admin"])
def open_phase(slug: SlugPath, phase: PhasePath, admin: AdminDep, db: DBDep) -> ChallengeOut:
    """Open the phase now (admins); a closed one opens again, with no close date."""
    service.open_phase(db, slug=slug, phase=phase, by=admin)
    db.commit()
    return challenge_detail(slug, Caller(user=admin, session=None), db)


def _verification(challenge: Challenge) -> VerificationOut | None:
    found = stored_verification(challenge.verification)
    if found is None:
        return None
    return VerificationOut(passed=found.passed, problems=found.problems, report=found.report)
