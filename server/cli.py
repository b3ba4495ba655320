"""Operator commands of the server: `manieval db upgrade`, `manieval admin create|users|
disable|enable|verify`, `manieval challenge load`, `challenge verify`, `challenge packages`,
`challenge teams`, `challenge set`, `challenge phase` and `challenge reevaluate` (the organizer's
other `admin` commands: `server/admin_cli.py`; `manieval serve` and `demo` compose it with the
worker: `manieval/serve.py`)."""

from __future__ import annotations

import getpass
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from pydantic import ValidationError
from rich.console import Console
from sqlalchemy.orm import Session, sessionmaker

from evaluator.suite import Suite, SuiteError

if TYPE_CHECKING:  # the evaluator's simulator is imported when `challenge verify` runs
    from evaluator.verification import VerificationReport
    from server.challenges.verification import Verification
from server.kit.errors import AppError
from server.kit.settings import Settings

if TYPE_CHECKING:
    from server.challenges.service import DateChange
    from server.models import Phase

console = Console(stderr=True, soft_wrap=True)

db_app = typer.Typer(help="Database schema.", no_args_is_help=True)
admin_app = typer.Typer(help="Administrators and organizer tools.", no_args_is_help=True)
challenge_app = typer.Typer(help="Challenges.", no_args_is_help=True)


def settings() -> Settings:
    try:
        return Settings()
    except ValidationError as exc:
        for error in exc.errors():
            console.print(f"[red]configuration error:[/] {error['msg']}")
        raise typer.Exit(2) from None


def migrated_sessions(s: Settings) -> sessionmaker[Session]:
    """Sessions of the configured database, after bringing its schema up to date."""
    from server.kit.db import make_engine, session_factory, upgrade

    upgrade(s.resolved_database_url)
    return session_factory(make_engine(s.resolved_database_url))


@contextmanager
def _transaction(s: Settings | None = None) -> Iterator[Session]:
    """One transaction on the configured (migrated) database; a refusal of the service's
    (`AppError`) ends the command with its message and exit status 1."""
    sessions = migrated_sessions(s or settings())
    try:
        with sessions.begin() as db:
            yield db
    except AppError as exc:
        console.print(f"[red]error:[/] {exc.message}")
        for field, problem in exc.fields.items():
            console.print(f"  {field}: {problem}", highlight=False)
        raise typer.Exit(1) from None


@db_app.command("upgrade")
def db_upgrade(revision: str = "head") -> None:
    """Apply migrations up to REVISION (default: the newest)."""
    from server.kit.db import upgrade

    s = settings()
    upgrade(s.resolved_database_url, revision)
    console.print(f"database at {revision}")


@admin_app.command("create")
def admin_create(
    username: str,
    email: str,
    password_stdin: Annotated[
        bool, typer.Option("--password-stdin", help="Read the password from standard input.")
    ] = False,
) -> None:
    """Create an administrator account (or make an existing user an administrator)."""
    from server.accounts import service as accounts

    s = settings()
    sessions = migrated_sessions(s)
    with sessions.begin() as db:
        existing = accounts.user_named(db, username=username)
        if existing is not None:
            existing.is_admin = True
            console.print(f"{username} is now an administrator")
            return
    password = (
        typer.get_text_stream("stdin").readline().rstrip("\n")
        if password_stdin
        else getpass.getpass(f"password for {username}: ")
    )
    try:
        with sessions.begin() as db:
            accounts.register(
                db,
                username=username,
                email=email,
                password=password,
                admin=True,
                min_score=s.password_min_score,
            )
    except AppError as exc:
        console.print(f"[red]error:[/] {exc.message}")
        for field, problem in exc.fields.items():
            console.print(f"  {field}: {problem}")
        raise typer.Exit(1) from None
    console.print(f"administrator {username} created")


@admin_app.command("users")
def admin_users(
    search: Annotated[str, typer.Argument(help="Part of a user name or address.")] = "",
    page: Annotated[int, typer.Option(min=1)] = 1,
) -> None:
    """List accounts, newest first: their state and submissions."""
    from server.accounts import service as accounts

    per_page = 50
    with _transaction() as db:
        rows, total = accounts.list_users(db, search=search, page=page, per_page=per_page)
        for row in rows:
            user = row.user
            state = ["verified" if user.email_verified else "unverified"]
            state += ["admin"] if user.is_admin else []
            disabled = f"\tdisabled: {user.disabled_reason}" if user.disabled_at else ""
            typer.echo(
                f"{user.id}\t{user.username}\t{user.email}\t{', '.join(state)}\t"
                f"{row.submissions} submissions{disabled}"
            )
    pages = max(1, -(-total // per_page))
    console.print(f"{total} accounts; page {page} of {pages}")


@admin_app.command("disable")
def admin_disable(
    username: Annotated[str, typer.Argument(help="The account's user name.")],
    reason: Annotated[str, typer.Option(help="Why: its owner is shown it.")],
) -> None:
    """Disable an account: it can no longer log in or use its tokens, its sessions end, and
    its queued and running submissions are cancelled."""
    from server.accounts.service import named_user
    from server.console.users import disable_account

    with _transaction() as db:
        cancelled = disable_account(
            db, user=named_user(db, username=username), by=None, reason=reason
        )
    console.print(f"{username} is disabled; {len(cancelled)} submissions cancelled")


@admin_app.command("enable")
def admin_enable(
    username: Annotated[str, typer.Argument(help="The account's user name.")],
    reason: Annotated[str, typer.Option(help="Why (optional).")] = "",
) -> None:
    """Let a disabled account log in and use its tokens again."""
    from server.accounts.service import enable_user, named_user

    with _transaction() as db:
        enable_user(db, user=named_user(db, username=username), by=None, reason=reason)
    console.print(f"{username} is enabled")


@admin_app.command("verify")
def admin_verify(
    username: Annotated[str, typer.Argument(help="The account's user name.")],
) -> None:
    """Mark an account's email address verified."""
    from server.accounts.service import mark_verified, named_user

    with _transaction() as db:
        mark_verified(db, user=named_user(db, username=username), by=None)
    console.print(f"the address of {username} is verified")


def _dates(values: list[str] | None, option: str) -> dict[str, datetime]:
    out: dict[str, datetime] = {}
    for value in values or []:
        phase, sep, when = value.partition("=")
        try:
            if not sep:
                raise ValueError("missing '='")
            parsed = datetime.fromisoformat(when)
        except ValueError:
            console.print(f"[red]error:[/] {option} takes PHASE=ISO-DATE, e.g. test=2027-01-31")
            raise typer.Exit(2) from None
        out[phase] = parsed if parsed.tzinfo else parsed.replace(tzinfo=UTC)
    return out


@challenge_app.command("load")
def challenge_load(
    suite: Annotated[str, typer.Argument(help="Suite file, or the name of a bundled suite.")],
    title: Annotated[str | None, typer.Option()] = None,
    quota_per_day: Annotated[int, typer.Option(min=1)] = 5,
    quota_concurrent: Annotated[int, typer.Option(min=1)] = 1,
    opens: Annotated[
        list[str] | None, typer.Option(help="PHASE=ISO-DATE when a phase opens (repeatable).")
    ] = None,
    closes: Annotated[
        list[str] | None, typer.Option(help="PHASE=ISO-DATE when a phase closes (repeatable).")
    ] = None,
    episodes: Annotated[
        int | None, typer.Option(min=1, help="Override every task's episodes (a try-out).")
    ] = None,
    teams: Annotated[
        bool | None,
        typer.Option(
            "--teams/--no-teams",
            help="Count quotas and leaderboard rows per team (default: as it is; off for a "
            "new challenge).",
            show_default=False,
        ),
    ] = None,
    unverified: Annotated[
        bool,
        typer.Option(
            "--unverified",
            help="Load it without a passing verification report beside the suite "
            "(`manieval challenge verify`); its page says so.",
        ),
    ] = False,
    track: Annotated[
        str | None, typer.Option(help="Its name as a track of its group (default: its own).")
    ] = None,
    track_of: Annotated[
        str | None, typer.Option(help="Make it a track of this challenge (the group's head).")
    ] = None,
    shared_quota: Annotated[
        bool | None,
        typer.Option(
            "--shared-quota/--quota-per-track",
            help="The group's tracks draw on one quota, the head's (default: as it is; per "
            "track at first).",
            show_default=False,
        ),
    ] = None,
    evaluator_image: Annotated[
        str | None,
        typer.Option(
            help="The evaluator image its Kubernetes Jobs run, REPO@sha256:DIGEST: one built "
            "with the suite's task packages and listed in the workers' "
            "MANIEVAL_EVALUATOR_IMAGES; 'default' for the workers' own (default: as it is).",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Create a challenge from a suite, or update the challenge of that name. The suite must
    have passed `manieval challenge verify` unless told `--unverified`."""
    from server.challenges.evaluator_image import evaluator_image_note
    from server.challenges.service import (
        ChallengeOptions,
        load_challenge,
        policy_refusal,
        suite_of,
    )
    from server.challenges.tracks import head_of, track_name, tracks_of
    from server.challenges.verification import Unverified, stored_verification

    s = settings()
    options = ChallengeOptions(
        title=title,
        quota_per_day=quota_per_day,
        quota_concurrent=quota_concurrent,
        opens=_dates(opens, "--opens"),
        closes=_dates(closes, "--closes"),
        episodes=episodes,
        teams=teams,
        verified_only=not unverified,
        track=track,
        track_of=track_of,
        quota_shared=shared_quota,
        evaluator_image=evaluator_image,
    )
    sessions = migrated_sessions(s)
    try:
        with sessions.begin() as db:
            challenge = load_challenge(
                db,
                Path(suite) if Path(suite).exists() else suite,
                options,
                seed_secret=s.secret("seed_secret"),
            )
            slug = challenge.slug
            phases = [(p.name, p.seed_commitment, _rules_line(p)) for p in challenge.phases]
            refusal = policy_refusal(challenge, policy_gpus=s.policy_gpus)
            loaded = suite_of(challenge)
            verification = stored_verification(challenge.verification)
            group = [f"{track_name(t)} ({t.slug})" for t in tracks_of(db, challenge)]
            shared = head_of(db, challenge).quota_shared
            image = challenge.evaluator_image
    except Unverified as exc:
        console.print(f"[red]error:[/] {exc.message}", highlight=False)
        console.print(
            f"verify it first (`manieval challenge verify {suite} --reference POLICY`), "
            "or load it with --unverified"
        )
        raise typer.Exit(1) from None
    except (SuiteError, AppError) as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(1) from None
    console.print(f"challenge {slug} loaded{' (teams)' if teams else ''}")
    _print_verification(slug, verification)
    _print_packages(loaded)
    for name, commitment, rules in phases:
        console.print(f"  phase {name}: seed commitment {commitment}; {rules}")
    if len(group) > 1:
        quota = "one quota shared" if shared else "a quota per track"
        console.print(f"  tracks: {', '.join(group)}; {quota}", highlight=False)
    if image is not None:
        console.print(f"  evaluator image {image}", highlight=False)
        console.print(f"note: {evaluator_image_note(image, queue=s.queue)}", highlight=False)
    if refusal is not None:
        # Loaded all the same: the GPUs may come later; until then submissions are refused.
        console.print(
            f"[yellow]warning:[/] {slug} refuses submissions until this service has the GPUs: "
            f"{refusal}",
            markup=True,
            highlight=False,
        )


def _rules_line(phase: Phase) -> str:
    """A phase's rules in words (docs/server.md, Challenge rules)."""
    words = [f"{phase.counts} counts"]
    if phase.final_choice:
        words.append("final choice")
    words.append(
        "late ones to a post-deadline board"
        if phase.after_close == "post_deadline"
        else "late ones refused"
    )
    words.append("board hidden until published" if phase.board == "hidden" else "board public")
    return ", ".join(words)


def _print_verification(slug: str, verification: Verification | None) -> None:
    """What the challenge's page will say of its verification."""
    if verification is None:
        return
    report = verification.report
    if verification.passed and report is not None:
        console.print(
            f"  verified by {report.reference}: {report.tasks[0].episodes} episodes a task on "
            f"the {report.phase} seeds, {report.created_at:%Y-%m-%d}",
            highlight=False,
        )
        return
    console.print(f"[yellow]warning:[/] {slug} is unverified (its page says so):")
    for problem in verification.problems:
        console.print(f"  {problem}", highlight=False)


def _print_packages(suite: Suite) -> None:
    """Each task package with the version loaded, and the package that registers each task
    (where ManiSkill is installed here to ask)."""
    from evaluator import packages

    for name, version in suite.package_versions.items():
        console.print(f"  package {name} {version}", highlight=False)
    if suite.packages and packages.simulator_installed():
        for env_id, provider in packages.resolve(suite).providers.items():
            console.print(f"  task {env_id}: {provider}", highlight=False)


@challenge_app.command("packages")
def challenge_packages(
    suite: Annotated[str, typer.Argument(help="Suite file, or the name of a bundled suite.")],
) -> None:
    """Import a suite's task packages here, say which one registers each task, and print the
    `package_versions` line to state in the suite (for a control plane without ManiSkill: run
    it in the evaluator image). Needs no database."""
    import json

    from evaluator import packages
    from evaluator.suite import load_suite

    try:
        pinned, _ = packages.pin(load_suite(suite))
        _print_packages(pinned)
    except SuiteError as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(1) from None
    print(f"package_versions: {json.dumps(pinned.package_versions)}")


@challenge_app.command("verify")
def challenge_verify(
    suite: Annotated[str, typer.Argument(help="Suite file, or the name of a bundled suite.")],
    reference: Annotated[
        str,
        typer.Option(
            help="The organizer's reference solution: a policy directory holding policy.py, "
            "or a bundled policy's name (scripted)."
        ),
    ],
    episodes: Annotated[
        int | None, typer.Option(min=1, help="Episodes per task (default: the suite's).")
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Write the report here [default: beside the suite, "
            "NAME.verification.json, where `challenge load` looks for it]."
        ),
    ] = None,
) -> None:
    """Run the reference solution (on 1, then 2 workers) and the random policy on the dev
    seeds, print each task's success, step headroom and cost, and write the report that
    `challenge load` asks for (docs/verification.md). Needs no database; exits 1 on failure."""
    from evaluator import packages
    from evaluator.suite import load_suite
    from evaluator.verification import report_path
    from evaluator.verify import reference_policy, verify

    ref = Path(suite) if Path(suite).exists() else suite
    try:
        policy = reference_policy(reference)
        pinned, _ = packages.pin(load_suite(ref))
        report = verify(
            pinned,
            policy,
            episodes=episodes,
            on_run=lambda name, plan: console.print(
                f"running the {name}: {plan.episode_count()} episodes"
            ),
        )
    except ValueError as exc:  # SuiteError among them
        console.print(f"[red]error:[/] {exc}", highlight=False)
        raise typer.Exit(2) from None
    target = out or report_path(ref)
    target.write_text(report.model_dump_json(indent=2) + "\n", encoding="utf-8")
    _print_report(report, target)
    if not report.passed:
        raise typer.Exit(1)


def _print_report(report: VerificationReport, target: Path) -> None:
    from server.challenges.verification import report_table

    # Whole rows in a log or a pipe too, where rich would assume 80 columns and cut names.
    Console(width=None if sys.stdout.isatty() else 140).print(report_table(report))
    for failure in report.failures:
        console.print(f"[red]failed:[/] {failure}", highlight=False)
    verdict = "passed" if report.passed else "FAILED"
    console.print(f"verification {verdict}; report written to {target}")


@challenge_app.command("teams")
def challenge_teams(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    mode: Annotated[str, typer.Argument(help="on: per team; off: per user.")],
) -> None:
    """Count a challenge's quotas and leaderboard rows per team (on) or per user (off)."""
    from server.challenges.service import set_team_mode

    if mode not in ("on", "off"):
        console.print("[red]error:[/] say on or off")
        raise typer.Exit(2)
    with _transaction() as db:
        set_team_mode(db, slug=slug, on=mode == "on")
    counted = "per team" if mode == "on" else "per user"
    console.print(f"challenge {slug}: quotas and leaderboard rows count {counted}")


@challenge_app.command("set")
def challenge_set(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    quota_per_day: Annotated[int | None, typer.Option(help="Submissions a day.")] = None,
    quota_concurrent: Annotated[int | None, typer.Option(help="Submissions at once.")] = None,
) -> None:
    """Change a challenge's quotas (what is not given stays as it is)."""
    from server.challenges.service import update_challenge

    with _transaction() as db:
        challenge = update_challenge(
            db,
            slug=slug,
            by=None,
            quota_per_day=quota_per_day,
            quota_concurrent=quota_concurrent,
        )
        per_day, concurrent = challenge.quota_per_day, challenge.quota_concurrent
    console.print(f"challenge {slug}: {per_day} submissions a day, {concurrent} at once")


def _date_option(value: str | None, option: str) -> DateChange:
    from server.challenges.service import KEEP

    if value is None:
        return KEEP
    if value.lower() == "none":
        return None
    try:
        return datetime.fromisoformat(value)
    except ValueError:
        console.print(f"[red]error:[/] {option} takes an ISO date (UTC unless it says), or none")
        raise typer.Exit(2) from None


@challenge_app.command("phase")
def challenge_phase(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    phase: Annotated[str, typer.Argument(help="The phase.")],
    opens: Annotated[str | None, typer.Option(help="ISO date it opens; none: always.")] = None,
    closes: Annotated[str | None, typer.Option(help="ISO date it closes; none: never.")] = None,
) -> None:
    """Move a phase's opening or closing date (closing now is `challenge close`)."""
    from server.challenges.service import update_phase

    opens_at, closes_at = _date_option(opens, "--opens"), _date_option(closes, "--closes")
    with _transaction() as db:
        found = update_phase(
            db, slug=slug, phase=phase, by=None, opens_at=opens_at, closes_at=closes_at
        )
        opens_when = f"{found.opens_at:%Y-%m-%d %H:%M} UTC" if found.opens_at else "always"
        closes_when = f"{found.closes_at:%Y-%m-%d %H:%M} UTC" if found.closes_at else "never"
    console.print(f"challenge {slug}: phase {phase} opens {opens_when}, closes {closes_when}")


@challenge_app.command("close")
def challenge_close(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    phase: Annotated[str, typer.Argument(help="The phase to close now.")],
) -> None:
    """Close a phase now: later submissions go by its `after_close` rule (refused, or to its
    post-deadline board), and final choices stand."""
    from server.challenges.service import close_phase

    with _transaction() as db:
        closed = close_phase(db, by=None, slug=slug, phase=phase)
        rule = closed.after_close
    late = "go to its post-deadline board" if rule == "post_deadline" else "are refused"
    console.print(f"challenge {slug}: phase {phase} closed; later submissions {late}")


@challenge_app.command("publish")
def challenge_publish(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    phase: Annotated[str, typer.Argument(help="The phase whose hidden board to publish.")],
) -> None:
    """Show a phase's hidden board (`board: hidden` in its suite) to everyone."""
    from server.challenges.service import publish_board

    with _transaction() as db:
        publish_board(db, by=None, slug=slug, phase=phase)
    console.print(f"challenge {slug}: the board of phase {phase} is public")


@challenge_app.command("reevaluate")
def challenge_reevaluate(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    phase: Annotated[
        str | None, typer.Option(help="Only this phase (default: every phase with entries).")
    ] = None,
) -> None:
    """Run every entry of a phase's board again on the current suite, into a new board version
    (nobody's quota; the previous version stays readable)."""
    from server.challenges.service import get_challenge, get_phase
    from server.submissions.reevaluation import NothingToReevaluate, Started, reevaluate

    s = settings()
    started: list[Started] = []
    skipped: list[str] = []
    with _transaction(s) as db:
        challenge = get_challenge(db, slug=slug)
        phases = [get_phase(challenge, phase)] if phase is not None else challenge.phases
        for target in phases:
            try:
                started.append(reevaluate(db, by=None, challenge=challenge, phase=target))
            except NothingToReevaluate:
                if phase is not None:
                    raise
                skipped.append(target.name)  # of every phase, those without entries
        if not started:
            raise AppError(f"no phase of {slug!r} has entries on its board to re-evaluate")
    for done in started:
        console.print(
            f"challenge {slug} phase {done.phase}: {len(done.submissions)} entries queued for "
            f"board version {done.board_version}; the current board stays until they end"
        )
    for name in skipped:
        console.print(f"challenge {slug} phase {name}: no entries, nothing to re-evaluate")
