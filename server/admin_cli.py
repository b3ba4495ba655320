"""The organizer's commands, run on the server's host against its database: `manieval admin
hide|unhide|disqualify|reinstate|rerun|rerun-stuck|export|audit|publish-token` (besides `admin
create`, in `server.cli`). Each action is recorded in the audit log with the login running the
command (`cli:LOGIN`); docs/server.md, Organizer tools."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from server.cli import _transaction, admin_app, console, settings

if TYPE_CHECKING:
    from server.submissions.moderation import Moderation

SubmissionId = Annotated[int, typer.Argument(help="The submission.", min=1)]
RequiredReason = Annotated[str, typer.Option("--reason", help="Why: its owner is shown it.")]
OptionalReason = Annotated[
    str, typer.Option("--reason", help="Why (optional): kept in the audit log.")
]


def _moderate(submission_id: int, action: Moderation, reason: str) -> None:
    from server.kit.errors import NotFound
    from server.models import Submission
    from server.submissions.moderation import moderate

    with _transaction() as db:
        s = db.get(Submission, submission_id)
        if s is None:
            raise NotFound(f"no submission {submission_id}")
        moderate(db, by=None, submission=s, action=action, reason=reason)
    console.print(f"submission {submission_id}: {action} done, its board recomputed")


@admin_app.command("hide")
def admin_hide(submission_id: SubmissionId, reason: RequiredReason = "") -> None:
    """Take a submission off every board, with the reason its owner is shown."""
    _moderate(submission_id, "hide", reason)


@admin_app.command("unhide")
def admin_unhide(submission_id: SubmissionId, reason: OptionalReason = "") -> None:
    """Put a hidden submission back on its board."""
    _moderate(submission_id, "unhide", reason)


@admin_app.command("disqualify")
def admin_disqualify(submission_id: SubmissionId, reason: RequiredReason = "") -> None:
    """Keep a submission on its board unranked, marked disqualified with the reason."""
    _moderate(submission_id, "disqualify", reason)


@admin_app.command("reinstate")
def admin_reinstate(submission_id: SubmissionId, reason: OptionalReason = "") -> None:
    """Rank a disqualified submission again."""
    _moderate(submission_id, "reinstate", reason)


@admin_app.command("rerun")
def admin_rerun(submission_id: SubmissionId, reason: OptionalReason = "") -> None:
    """Run an ended submission again as a new attempt (the server's sweep sends it to a
    worker)."""
    from server.kit.errors import NotFound
    from server.models import Submission
    from server.submissions.moderation import rerun

    with _transaction() as db:
        s = db.get(Submission, submission_id)
        if s is None:
            raise NotFound(f"no submission {submission_id}")
        rerun(db, admin=None, submission=s, reason=reason)
        attempt = s.attempt
    console.print(f"submission {submission_id}: queued again as attempt {attempt}")


@admin_app.command("rerun-stuck")
def admin_rerun_stuck(
    challenge: Annotated[
        str | None, typer.Option(help="Only this challenge's (default: every challenge's).")
    ] = None,
    reason: OptionalReason = "",
) -> None:
    """End every stuck evaluation (past its deadline, or silent past the heartbeat timeout)
    as `error` and queue it again as a new attempt, now."""
    from server.challenges.service import get_challenge
    from server.cli import settings
    from server.submissions.moderation import rerun_stuck
    from server.submissions.reconcile import timeouts_of

    s = settings()
    with _transaction(s) as db:
        found = get_challenge(db, slug=challenge) if challenge is not None else None
        timeouts = timeouts_of(s)
        queued = rerun_stuck(db, by=None, challenge=found, timeouts=timeouts, reason=reason)
    if not queued:
        console.print("nothing is stuck")
        return
    listed = ", ".join(str(sid) for sid in queued)
    console.print(f"queued again as new attempts: {listed}")


@admin_app.command("export")
def admin_export(
    slug: Annotated[str, typer.Argument(help="The challenge.")],
    phase: Annotated[str | None, typer.Option(help="Only this phase's submissions.")] = None,
    format: Annotated[str, typer.Option("--format", help="csv or json.")] = "csv",
    out: Annotated[
        Path | None, typer.Option("--out", help="Write to this file (default: standard output).")
    ] = None,
) -> None:
    """Every submission of a challenge with its result, one row each (as the API's export)."""
    from server.challenges.service import get_challenge, get_phase
    from server.submissions.export import ExportFormat, export_text

    if format not in ("csv", "json"):
        console.print("[red]error:[/] --format is csv or json")
        raise typer.Exit(2)
    shape: ExportFormat = "json" if format == "json" else "csv"
    with _transaction() as db:
        challenge = get_challenge(db, slug=slug)
        only = get_phase(challenge, phase) if phase is not None else None
        text = export_text(db, challenge=challenge, phase=only, format=shape)
        if out is None:
            sys.stdout.writelines(text)
            return
        with out.open("w", encoding="utf-8", newline="") as file:
            file.writelines(text)
    console.print(f"wrote {out}")


@admin_app.command("audit")
def admin_audit(
    challenge: Annotated[str | None, typer.Option(help="Only this challenge's.")] = None,
    action: Annotated[str | None, typer.Option(help="Only this action (phase.close).")] = None,
    before_id: Annotated[int | None, typer.Option(help="Older than this record.")] = None,
    limit: Annotated[int, typer.Option(help="How many (newest first).", min=1)] = 50,
) -> None:
    """Print the organizers' actions, newest first: when, who, what, on what, and why."""
    from server.submissions.audit_log import audit_listing

    with _transaction() as db:
        listing = audit_listing(
            db, challenge=challenge, action=action, before_id=before_id, limit=limit
        )
        for entry in listing.entries:
            r = entry.record
            target = f"{r.target_kind} {r.target_id}" if r.target_id is not None else r.target_kind
            where = f" [{entry.challenge}]" if entry.challenge else ""
            why = f": {r.reason}" if r.reason else ""
            when = f"{r.at:%Y-%m-%d %H:%M:%S}"
            typer.echo(f"{r.id}\t{when}\t{r.actor}\t{r.action} {target}{where}{why}")
    if listing.next_before_id is not None:
        console.print(f"older: --before-id {listing.next_before_id}")


@admin_app.command("publish-token")
def admin_publish_token(
    repository: Annotated[
        str | None,
        typer.Argument(
            help="A repository under manieval/ [default: the policy base's].", show_default=False
        ),
    ] = None,
    reason: OptionalReason = "",
) -> None:
    """Print a push token for one repository of the service's own namespace, for publishing
    the policy base to a registry the service does not start (docs/registry.md)."""
    from server.audit import reason_of, record
    from server.registry.published import LOCAL_POLICY_BASE, POLICY_BASE_REPOSITORY, POLICY_BASE_TAG
    from server.registry.service import publish_token

    repository = repository or POLICY_BASE_REPOSITORY
    s = settings()
    if s.registry_domain is None:
        console.print("[red]error:[/] this service has no registry (MANIEVAL_REGISTRY_DOMAIN)")
        raise typer.Exit(2)
    try:
        token = publish_token(s, repository=repository)
    except ValueError as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(2) from None
    with _transaction(s) as db:
        why = reason_of(reason, required=False)
        record(
            db,
            by=None,
            action="registry.publish_token",
            target_kind="repository",
            target_id=None,
            reason=why,
            detail={"repository": repository},
        )
    typer.echo(token)
    target = f"docker://{s.registry_domain}/{repository}:{POLICY_BASE_TAG}"
    console.print(
        f"valid for {s.registry_token_ttl_s} s, e.g.: skopeo copy --dest-registry-token TOKEN "
        f"containers-storage:{LOCAL_POLICY_BASE} {target}",
        markup=False,
        highlight=False,
    )
