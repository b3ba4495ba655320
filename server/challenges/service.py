"""Challenges: created or updated from a suite file; the test phase's seeds stay on the server."""

from __future__ import annotations

import enum
import hashlib
import hmac
import json
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import yaml
from sqlalchemy import func, select
from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import selectinload

from evaluator import packages
from evaluator.suite import Phase as SuitePhase
from evaluator.suite import PublicSeeds, Suite, load_suite, phase_seeds, seed_commitment
from server import audit
from server.challenges.evaluator_image import chosen_evaluator_image
from server.challenges.tracks import head_of, join_group
from server.challenges.verification import Unverified, suite_verification
from server.kit.errors import Conflict, Invalid, NotFound
from server.models import Challenge, Phase, User, utcnow
from server.standings.entries import rebuild


@dataclass(frozen=True)
class ChallengeOptions:
    title: str | None = None
    description: str | None = None
    quota_per_day: int = 5
    quota_concurrent: int = 1
    opens: dict[str, datetime] = field(default_factory=dict)
    closes: dict[str, datetime] = field(default_factory=dict)
    episodes: int | None = None
    """Override every task's episode count (a quick try-out; the stored suite says so)."""
    tasks: tuple[str, ...] | None = None
    """Only these of the suite's tasks (a try-out, as `episodes`; None: all)."""
    conditions: tuple[str, ...] | None = None
    """Only these of the suite's conditions (a try-out, as `episodes`; None: all)."""
    teams: bool | None = None
    """Count quotas and leaderboard rows per team (None: as it is; off for a new challenge)."""
    verified_only: bool = False
    """Refuse a suite without a passing verification report beside it (Unverified), as
    `manieval challenge load` does unless told `--unverified`; either way the report, or its
    absence, is kept for the challenge's page."""
    track: str | None = None
    """The challenge's name within its group of tracks (None: as it is; its slug when unset)."""
    track_of: str | None = None
    """Make the challenge a track of this one, the group's head (None: as it is)."""
    quota_shared: bool | None = None
    """Whether the group's tracks share the head's quota (None: as it is; off at first)."""
    evaluator_image: str | None = None
    """The challenge's own evaluator image, pinned by digest (`evaluator_image.WORKERS_OWN`:
    none; None: as it is, unless the suite's task packages changed: `chosen_evaluator_image`)."""


def load_challenge(
    db: DB, suite_ref: str | Path, options: ChallengeOptions, *, seed_secret: str
) -> Challenge:
    """Create the challenge named after the suite, or update it in place (same slug)."""
    suite = load_suite(suite_ref)
    for name in [*options.opens, *options.closes]:
        suite.phase(name)  # SuiteError names the phases that exist
    _check_quotas(quota_per_day=options.quota_per_day, quota_concurrent=options.quota_concurrent)
    text = Path(suite_ref).read_text() if Path(suite_ref).exists() else None
    suite_yaml = text if text is not None else _bundled_text(suite_ref)
    stated = suite.package_versions
    suite, _ = packages.pin(suite)  # TaskPackageError: missing, failing, another version
    if suite.package_versions != stated:
        suite_yaml = with_package_versions(suite_yaml, suite.package_versions)
    verification = suite_verification(suite_ref, suite)  # of the suite as written, not narrowed
    if options.verified_only and not verification.passed:
        raise Unverified(suite.name, verification.problems)
    suite, narrowed = try_out(suite, options)
    if narrowed:
        header = f"# {suite.name} with {', '.join(narrowed)} (a try-out)\n"
        suite_yaml = header + yaml.safe_dump(suite.model_dump(mode="json"), sort_keys=False)

    challenge = db.scalar(
        select(Challenge)
        .options(selectinload(Challenge.phases))
        .where(Challenge.slug == suite.name)
    )
    kept_versions = {} if challenge is None else suite_of(challenge).package_versions
    before = {} if challenge is None else _loaded_of(db, challenge)
    if challenge is None:
        challenge = Challenge(slug=suite.name)
        db.add(challenge)
    challenge.evaluator_image = chosen_evaluator_image(
        given=options.evaluator_image,
        kept=challenge.evaluator_image,
        kept_versions=kept_versions,
        suite=suite,
    )
    # A suite's own `title` (when its schema has one) wins over the name made readable.
    challenge.title = options.title or display_title(suite.name, suite.title or None)
    challenge.description = options.description or suite.description
    challenge.suite_yaml = suite_yaml
    challenge.suite_hash = suite.sha256()
    challenge.verification = verification.stored()
    challenge.quota_per_day = options.quota_per_day
    challenge.quota_concurrent = options.quota_concurrent
    regroup = options.teams is not None and challenge.team_mode != options.teams
    challenge.team_mode = bool(options.teams if options.teams is not None else challenge.team_mode)

    existing = {phase.name: phase for phase in challenge.phases}
    for name, spec in suite.phases.items():
        phase = existing.pop(name, None)
        if phase is None:
            phase = Phase(name=name, significance_level=spec.significance_level)
            phase.counts, phase.final_choice, phase.after_close, phase.board = _rules_of(spec)
            challenge.phases.append(phase)
        elif phase.significance_level != spec.significance_level:
            # The tie groups change with the level: readers of the board read it again.
            phase.significance_level = spec.significance_level
            phase.leaderboard_version += 1
        if _rules_of(phase) != _rules_of(spec):
            phase.counts, phase.final_choice, phase.after_close, phase.board = _rules_of(spec)
            # Who stands on the board, and who sees it, changed: its rows are recomputed.
            regroup = True
        phase.public_seeds = isinstance(spec.seeds, PublicSeeds)
        phase.seed_commitment = commitment(suite, name, seed_secret)
        # In UTC, as the database gives them back (a reload then compares like with like).
        if name in options.opens:
            phase.opens_at = _utc(options.opens[name], f"opens of {name}")
        if name in options.closes:
            phase.closes_at = _utc(options.closes[name], f"closes of {name}")
        if phase.opens_at and phase.closes_at and phase.closes_at <= phase.opens_at:
            raise Invalid(f"phase {name!r} closes before it opens")
    for gone in existing.values():  # phases dropped from the suite
        challenge.phases.remove(gone)
    db.flush()
    join_group(
        db,
        challenge,
        track=options.track,
        track_of=options.track_of,
        quota_shared=options.quota_shared,
    )
    if regroup:
        rebuild(db, challenge_id=challenge.id)
    after = _loaded_of(db, challenge)
    every = [*before, *(name for name in after if name not in before)]
    _record_change(
        db,
        by=None,  # `manieval challenge load` (or the demo's) on the server's host
        action="challenge.load",
        target=challenge,
        before={name: before.get(name) for name in every},  # a new challenge or phase: None
        after={name: after.get(name) for name in every},  # a phase dropped: None
    )
    return challenge


def _loaded_of(db: DB, challenge: Challenge) -> dict[str, Any]:
    """What a load sets, as its audit record compares it (a phase's under ``phase NAME``): a
    reload that changes nothing leaves no record (the demo reloads its examples at every
    start)."""
    head = head_of(db, challenge)
    return {
        "suite_sha256": challenge.suite_hash,
        "title": challenge.title,
        "evaluator_image": challenge.evaluator_image,
        **_settings_of(challenge),
        "track": challenge.track,
        "track_of": None if head is challenge else head.slug,
        "quota_shared": head.quota_shared,  # the group's, held by its head
        **{f"phase {phase.name}": _phase_loaded(phase) for phase in challenge.phases},
    }


def _phase_loaded(phase: Phase) -> dict[str, Any]:
    counts, final_choice, after_close, board = _rules_of(phase)
    rules = {"counts": counts, "final_choice": final_choice, "after_close": after_close}
    rules |= {"board": board, "significance_level": phase.significance_level}
    return {**_dates_of(phase), **rules}


def _rules_of(phase: Phase | SuitePhase) -> tuple[str, bool, str, str]:
    return (phase.counts, phase.final_choice, phase.after_close, phase.board)


def close_phase(
    db: DB, *, by: User | None, slug: str, phase: str, now: datetime | None = None
) -> Phase:
    """Close the phase now (an organizer's action, `by` an admin or None: the command line,
    recorded): a submission racing it is either made before the close or goes by the phase's
    `after_close` rule, never onto the official board after it (the submit path holds the
    phase's row, `lock_phase`)."""
    found = get_phase(get_challenge(db, slug=slug), phase)
    locked = lock_phase(db, phase_id=found.id, write=True)
    now = now or utcnow()  # read once the lock is ours: every submit before it is earlier
    if locked.closes_at is not None and locked.closes_at <= now:
        raise Conflict(
            f"phase {phase!r} of {slug!r} closed at {locked.closes_at:%Y-%m-%d %H:%M} UTC"
        )
    if locked.opens_at is not None and now < locked.opens_at:
        locked.opens_at = now  # a phase closed before it opened never opened
    locked.closes_at = now
    _record(db, by, locked, "phase.close", {"phase": locked.name, "closes_at": now.isoformat()})
    db.flush()
    return locked


def _record(db: DB, by: User | None, phase: Phase, action: str, detail: dict[str, Any]) -> None:
    audit.record(
        db,
        by=by,
        action=action,
        target_kind="phase",
        target_id=phase.id,
        challenge_id=phase.challenge_id,
        detail=detail,
    )


def lock_phase(db: DB, *, phase_id: int, write: bool = False) -> Phase:
    """The phase's row, read again under a lock: shared for a submit (submits do not wait on
    each other), else the lock an update of the row takes (`FOR NO KEY UPDATE`: a change of
    its dates; a final mark, whose board refresh updates the row, so that two marks never
    both hold it shared and then wait on each other to update it)."""
    locked = db.scalar(
        select(Phase)
        .where(Phase.id == phase_id)
        .with_for_update(read=not write, key_share=write)
        .execution_options(populate_existing=True)
    )
    if locked is None:
        raise NotFound(f"no phase {phase_id}")
    return locked


def publish_board(
    db: DB, *, by: User | None, slug: str, phase: str, now: datetime | None = None
) -> Phase:
    """Show the phase's hidden board to everyone (an organizer's action, recorded as
    `close_phase`'s; publishing twice keeps the first date and records nothing)."""
    found = get_phase(get_challenge(db, slug=slug), phase)
    if found.board != "hidden":
        raise Conflict(f"phase {phase!r} of {slug!r} has a public board: nothing to publish")
    if found.published_at is None:
        found.published_at = now or utcnow()
        found.leaderboard_version += 1  # cached snapshots were the hidden board's
        _record(db, by, found, "phase.publish", {"phase": found.name})
        db.flush()
    return found


def set_team_mode(db: DB, *, slug: str, on: bool) -> Challenge:
    """Count the challenge's quotas and leaderboard rows per team (on) or per user (off);
    its boards are recomputed at once (docs/server.md, Teams)."""
    challenge = get_challenge(db, slug=slug)
    _switch_team_mode(db, challenge, on=on)
    return challenge


def _switch_team_mode(db: DB, challenge: Challenge, *, on: bool) -> None:
    if challenge.team_mode != on:
        challenge.team_mode = on
        db.flush()
        rebuild(db, challenge_id=challenge.id)


# Settings an organizer changes on a running challenge (the console, the API, the CLI) ----------

QUOTA_MAX = 10_000
"""The largest quota accepted: more is no limit, and the column is a 32-bit integer."""


class _Keep(enum.Enum):
    KEEP = "keep"


KEEP: Literal[_Keep.KEEP] = _Keep.KEEP
"""A date left as it is (None clears it)."""
DateChange = datetime | None | Literal[_Keep.KEEP]


def update_challenge(
    db: DB,
    *,
    slug: str,
    by: User | None,
    quota_per_day: int | None = None,
    quota_concurrent: int | None = None,
    team_mode: bool | None = None,
) -> Challenge:
    """Change the challenge's quotas or team mode (None: as it is); a change of team mode
    recomputes its boards. Audited with the old and new values of what changed."""
    _check_quotas(quota_per_day=quota_per_day, quota_concurrent=quota_concurrent)
    challenge = get_challenge(db, slug=slug)
    before = _settings_of(challenge)
    if quota_per_day is not None:
        challenge.quota_per_day = quota_per_day
    if quota_concurrent is not None:
        challenge.quota_concurrent = quota_concurrent
    if team_mode is not None:
        _switch_team_mode(db, challenge, on=team_mode)
    _record_change(
        db,
        by=by,
        action="challenge.settings",
        target=challenge,
        before=before,
        after=_settings_of(challenge),
    )
    return challenge


def _check_quotas(**quotas: int | None) -> None:
    """Invalid unless each quota given is a whole number from 1 to `QUOTA_MAX`."""
    problems = {
        name: f"a whole number from 1 to {QUOTA_MAX}"
        for name, value in quotas.items()
        if value is not None and not 1 <= value <= QUOTA_MAX
    }
    if problems:
        named = ", ".join(f"{name} must be {want}" for name, want in problems.items())
        raise Invalid(f"the challenge's settings are not valid: {named}", fields=problems)


def _settings_of(challenge: Challenge) -> dict[str, Any]:
    return {
        "quota_per_day": challenge.quota_per_day,
        "quota_concurrent": challenge.quota_concurrent,
        "team_mode": challenge.team_mode,
    }


def _record_change(
    db: DB,
    *,
    by: User | None,
    action: str,
    target: Challenge | Phase,
    before: dict[str, Any],
    after: dict[str, Any],
) -> None:
    """The audit record of a change of settings, with the old and new value of each that
    changed; nothing when none did."""
    changed = [name for name in before if before[name] != after[name]]
    if not changed:
        return
    if isinstance(target, Phase):
        kind, challenge_id, which = "phase", target.challenge_id, {"phase": target.name}
    else:
        kind, challenge_id, which = "challenge", target.id, {}
    audit.record(
        db,
        by=by,
        action=action,
        target_kind=kind,
        target_id=target.id,
        challenge_id=challenge_id,
        detail={
            **which,
            "old": {name: before[name] for name in changed},
            "new": {name: after[name] for name in changed},
        },
    )
    db.flush()


def update_phase(
    db: DB,
    *,
    slug: str,
    phase: str,
    by: User | None,
    opens_at: DateChange = KEEP,
    closes_at: DateChange = KEEP,
    now: datetime | None = None,
) -> Phase:
    """Move the phase's opening or closing date (None: no such date). Holds the phase's row as
    a close does, so a submission racing the change goes by the dates before it or after it.
    A new close date must be after the opening and not in the past: closing now is
    `close_phase`'s."""
    found = get_phase(get_challenge(db, slug=slug), phase)
    locked = lock_phase(db, phase_id=found.id, write=True)
    now = now or utcnow()
    before = _dates_of(locked)
    opens = locked.opens_at if opens_at is KEEP else _utc(opens_at, "opens_at")
    closes = locked.closes_at if closes_at is KEEP else _utc(closes_at, "closes_at")
    problems: dict[str, str] = {}
    if closes is not None and closes != locked.closes_at and closes <= now:
        problems["closes_at"] = "is in the past: to close the phase now, use close now"
    if opens is not None and closes is not None and closes <= opens:
        problems["closes_at"] = "must be after the opening date"
    if problems:
        raise Invalid(f"phase {phase!r} of {slug!r}: the dates are not valid", fields=problems)
    locked.opens_at, locked.closes_at = opens, closes
    _record_change(
        db, by=by, action="phase.settings", target=locked, before=before, after=_dates_of(locked)
    )
    return locked


def open_phase(
    db: DB, *, slug: str, phase: str, by: User | None, now: datetime | None = None
) -> Phase:
    """Open the phase now: one not yet open opens; a closed one opens again, with no close date
    (set one after). Holds the phase's row as a close does."""
    found = get_phase(get_challenge(db, slug=slug), phase)
    locked = lock_phase(db, phase_id=found.id, write=True)
    now = now or utcnow()
    if locked.is_open(now):
        raise Conflict(f"phase {phase!r} of {slug!r} is open already")
    before = _dates_of(locked)
    if not locked.has_opened(now):
        locked.opens_at = now
    if locked.closes_at is not None and locked.closes_at <= now:
        locked.closes_at = None
    _record_change(
        db, by=by, action="phase.open", target=locked, before=before, after=_dates_of(locked)
    )
    return locked


def _dates_of(phase: Phase) -> dict[str, str | None]:
    return {
        "opens_at": phase.opens_at.isoformat() if phase.opens_at else None,
        "closes_at": phase.closes_at.isoformat() if phase.closes_at else None,
    }


def _utc(value: datetime | None, name: str) -> datetime | None:
    """`value` in UTC (a date without a zone is read as UTC), or Invalid for `name`."""
    if value is None:
        return None
    try:
        found = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
    except OverflowError:
        found = None
    if found is None or not 1970 <= found.year <= 9000:
        raise Invalid(f"{name} is out of range", fields={name: "a date from 1970 to 9000"})
    return found


def try_out(suite: Suite, options: ChallengeOptions) -> tuple[Suite, list[str]]:
    """The suite narrowed to the options' tasks, conditions and episode count, and what was
    narrowed, in words (nothing: the suite as it is)."""
    narrowed: list[str] = []
    tasks = suite.tasks
    if options.tasks is not None:
        tasks = tuple(suite.task(name) for name in options.tasks)  # SuiteError names the tasks
        narrowed.append(f"only the task{'s' if len(tasks) > 1 else ''} {', '.join(options.tasks)}")
    if options.episodes is not None:
        if options.episodes < 1:
            raise Invalid("episodes must be at least 1")
        tasks = tuple(t.model_copy(update={"episodes": options.episodes}) for t in tasks)
        narrowed.append(f"{options.episodes} episodes per task")
    update: dict[str, object] = {"tasks": tasks}
    if options.conditions is not None:
        kept = tuple(suite.condition(name) for name in options.conditions)
        filmed = suite.video_conditions
        update["conditions"] = kept
        update["video_conditions"] = filmed and tuple(c for c in filmed if c in options.conditions)
        plural = "s" if len(kept) > 1 else ""
        narrowed.append(f"only the condition{plural} {', '.join(options.conditions)}")
    if not narrowed:
        return suite, []
    if not tasks or not update.get("conditions", True):
        raise Invalid("a try-out keeps at least one task and one condition")
    return Suite.model_validate({**suite.model_dump(), **update}), narrowed


def with_package_versions(suite_yaml: str, versions: dict[str, str]) -> str:
    """The suite's text with the versions its packages were loaded with as its
    `package_versions`: appended, with the author's comments kept, unless the text has the key
    (empty), in which case the suite is written out again."""
    note = "# Recorded by `manieval challenge load`: the task packages' versions where it ran.\n"
    raw = yaml.safe_load(suite_yaml)
    if isinstance(raw, dict) and "package_versions" in raw:
        return note + yaml.safe_dump({**raw, "package_versions": versions}, sort_keys=False)
    return f"{suite_yaml.rstrip()}\n{note}package_versions: {json.dumps(versions)}\n"


def _bundled_text(ref: str | Path) -> str:
    from evaluator.suite import SUITES_DIR

    return (SUITES_DIR / f"{ref}.yaml").read_text()


# Words a suite's name spells in lower case that are written otherwise (brands, acronyms).
KNOWN_WORDS = {
    "maniskill": "ManiSkill",
    "maniskill2": "ManiSkill2",
    "maniskill3": "ManiSkill3",
    "sapien": "SAPIEN",
    "ycb": "YCB",
    "rgb": "RGB",
    "rgbd": "RGBD",
    "cpu": "CPU",
    "gpu": "GPU",
}


def display_title(name: str, declared: str | None = None) -> str:
    """The title a suite declares, else its name made readable: "maniskill-core" reads
    "ManiSkill Core"; known brands keep their casing and other words only gain a capital."""
    if declared:
        return declared
    words = name.replace("_", " ").replace("-", " ").split()
    return " ".join(KNOWN_WORDS.get(w, w[:1].upper() + w[1:]) for w in words)


def suite_of(challenge: Challenge) -> Suite:
    """The suite the challenge was loaded from, as stored with it."""
    return Suite.model_validate(yaml.safe_load(challenge.suite_yaml))


class GpusUnavailable(Conflict):
    """The challenge's suite gives each policy more GPUs than this service has for one: its
    submissions could never run, so they are refused rather than queued."""

    code = "gpus_unavailable"


def policy_refusal(challenge: Challenge, *, policy_gpus: int) -> str | None:
    """Why a service that gives a policy at most `policy_gpus` GPUs cannot evaluate the
    challenge's submissions, or None."""
    return suite_of(challenge).policy.refusal(available=policy_gpus)


def check_servable(challenge: Challenge, *, policy_gpus: int) -> None:
    """GpusUnavailable, with the reason, if the challenge's policies need GPUs this service
    does not have (`MANIEVAL_POLICY_GPUS`)."""
    refusal = policy_refusal(challenge, policy_gpus=policy_gpus)
    if refusal is not None:
        raise GpusUnavailable(refusal)


def phase_seed_map(suite: Suite, phase: str, seed_secret: str) -> dict[str, list[int]]:
    """Each task's seeds in a phase (secret ones derived from `seed_secret`)."""
    secret = seed_secret.encode()  # the HMAC mixes in the suite's name: no shared seeds
    return {
        task.env_id: phase_seeds(suite, phase, task.env_id, task.episodes, secret=secret)
        for task in suite.tasks
    }


def commitment(suite: Suite, phase: str, seed_secret: str) -> str:
    """SHA-256 over the phase's seeds and a secret salt, published before seeds are revealed."""
    salt = hmac.new(
        seed_secret.encode(), f"salt/{suite.name}/{phase}".encode(), hashlib.sha256
    ).hexdigest()
    return seed_commitment(phase_seed_map(suite, phase, seed_secret), salt=salt)


def get_challenge(db: DB, *, slug: str) -> Challenge:
    """The challenge with this slug, with its phases, or NotFound."""
    challenge = db.scalar(
        select(Challenge).options(selectinload(Challenge.phases)).where(Challenge.slug == slug)
    )
    if challenge is None:
        raise NotFound(f"no challenge {slug!r}")
    return challenge


def get_phase(challenge: Challenge, name: str) -> Phase:
    """The challenge's phase of this name, or Invalid naming the phases it has."""
    for phase in challenge.phases:
        if phase.name == name:
            return phase
    names = ", ".join(p.name for p in challenge.phases)
    raise Invalid(
        f"challenge {challenge.slug!r} has no phase {name!r} (it has: {names})",
        fields={"phase": f"one of: {names}"},
    )


def shown_phase(challenge: Challenge, *, name: str | None) -> Phase:
    """The phase a page shows: the one named (NotFound if none is), else the first phase open
    now, else the first one."""
    if name is None:
        now = utcnow()
        return next((p for p in challenge.phases if p.is_open(now)), challenge.phases[0])
    try:
        return get_phase(challenge, name)
    except Invalid:
        raise NotFound(f"challenge {challenge.slug!r} has no phase {name!r}") from None


def list_challenges(db: DB, *, page: int, per_page: int) -> tuple[list[Challenge], int]:
    """One page of the challenges with their phases, oldest first, and how many there are."""
    total = db.scalar(select(func.count()).select_from(Challenge)) or 0
    rows = db.scalars(
        select(Challenge)
        .options(selectinload(Challenge.phases))
        .order_by(Challenge.id)
        .offset((page - 1) * per_page)
        .limit(per_page)
    )
    return list(rows), total


def all_challenges(db: DB) -> list[Challenge]:
    """Every challenge with its phases, oldest first (the home page lists them all)."""
    return list(
        db.scalars(select(Challenge).options(selectinload(Challenge.phases)).order_by(Challenge.id))
    )
