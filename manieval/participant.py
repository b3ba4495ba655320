"""The participant commands that take part in challenges: challenges, leaderboard, submit,
status, logs, trajectories and cancel. Like the account commands (manieval/account.py) they
speak to the server's public API only; docs/cli.md describes them with their exit codes."""

from __future__ import annotations

import enum
import re
import sys
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.text import Text

from manieval import render
from manieval.client import Client, MethodInfo
from manieval.connect import JsonOption, ServerOption, connect, print_json
from manieval.errors import STATE_CODES, ExitCode, fail, handled, server_flag
from manieval.follow import FINAL_STATES, follow

FILE_NAME = re.compile(r"[A-Za-z0-9_\-]+\.(h5|json)")
SubmissionId = Annotated[int, typer.Argument(min=1, help="The submission's number.")]
MethodOption = Annotated[
    str | None, typer.Option("--method", help="Your method's name, shown on the leaderboard.")
]
PaperOption = Annotated[
    str | None, typer.Option("--paper-url", help="A link to the method's paper (http or https).")
]
CodeOption = Annotated[
    str | None, typer.Option("--code-url", help="A link to the method's code (http or https).")
]


# Challenges -----------------------------------------------------------------------------------


def challenges(server: ServerOption = None, as_json: JsonOption = False) -> None:
    """List the challenges and their phases."""
    with handled(), connect(server, login="none") as client:
        items = client.challenges()
    if as_json:
        print_json(items)
    elif not items:
        render.stderr().print(f"no challenges on {client.server} yet")
    else:
        render.stdout().print(render.challenges_table(items))


class BoardFormat(enum.StrEnum):
    TABLE = "table"
    JSON = "json"
    CSV = "csv"
    MARKDOWN = "markdown"
    LATEX = "latex"


def leaderboard(
    challenge: Annotated[str, typer.Argument(help="The challenge's name.")],
    phase: Annotated[str, typer.Option(help="The phase.")] = "dev",
    page: Annotated[int, typer.Option(min=1, help="Which page of rows.")] = 1,
    per_page: Annotated[int, typer.Option(min=1, max=200, help="Rows per page.")] = 50,
    as_json: JsonOption = False,
    as_csv: Annotated[
        bool, typer.Option("--csv", help="Print CSV, as the server renders it.")
    ] = False,
    format: Annotated[
        BoardFormat,
        typer.Option(
            "--format",
            help="table: for the terminal; json, csv: as the server renders them; markdown, "
            "latex: a table for a paper (success with intervals, tie groups, provenance).",
        ),
    ] = BoardFormat.TABLE,
    server: ServerOption = None,
) -> None:
    """Show a challenge's leaderboard: the best public submission of each participant."""
    chosen = [f for f, on in ((BoardFormat.JSON, as_json), (BoardFormat.CSV, as_csv)) if on]
    if format is not BoardFormat.TABLE:
        chosen.append(format)
    if len(chosen) > 1:
        raise typer.BadParameter("choose one of --json, --csv and --format", param_hint="--format")
    shown = chosen[0] if chosen else BoardFormat.TABLE
    asked = "json" if shown is BoardFormat.TABLE else shown.value
    # Your token, where one is saved: a hidden board shows you your own rows.
    with handled(), connect(server, login="optional") as client:
        response = client.leaderboard(
            challenge, phase=phase, page=page, per_page=per_page, format=asked
        )
    if shown is not BoardFormat.TABLE:
        render.write_raw(response.content)
        return
    board = response.json()
    if not board["items"]:
        render.stderr().print(f"no ranked submissions on {challenge} ({phase}) yet")
        return
    render.stdout().print(render.leaderboard_table(board))


# Submissions ----------------------------------------------------------------------------------


def submit(
    image: Annotated[str, typer.Argument(help="Image reference: registry/repo:tag or @sha256:...")],
    challenge: Annotated[str, typer.Option("--challenge", "-c", help="The challenge's name.")],
    phase: Annotated[str, typer.Option(help="The phase.")] = "dev",
    track: Annotated[
        str | None,
        typer.Option(help="The challenge's track, by name (state, visual) or challenge name."),
    ] = None,
    description: Annotated[str, typer.Option(help="A note shown with the submission.")] = "",
    method: MethodOption = None,
    paper_url: PaperOption = None,
    code_url: CodeOption = None,
    private: Annotated[
        bool, typer.Option("--private", help="Keep it off the public leaderboard.")
    ] = False,
    wait: Annotated[
        bool, typer.Option("--wait", help="Follow it to its end; exit 0 only if it succeeds.")
    ] = False,
    as_json: JsonOption = False,
    server: ServerOption = None,
) -> None:
    """Submit a policy image to a challenge (its tag is pinned to a digest at once)."""
    with handled(), connect(server, login="required") as client:
        s = client.submit(
            challenge=challenge,
            phase=phase,
            image=image,
            description=description,
            public=not private,
            method=MethodInfo(method, paper_url, code_url),
            track=track,
        )
        err = render.stderr()
        err.print(f"submission {s['id']} accepted: {s['pinned_image']}")
        if not wait:
            if as_json:
                print_json(s)
            err.print(f"follow it: manieval status {s['id']} --wait{server_flag(client.server)}")
            return
        wait_and_report(client, s["id"], as_json=as_json)


def wait_and_report(client: Client, submission_id: int, *, as_json: bool) -> NoReturn:
    """Follow to the end, print the outcome, exit with the final state's code."""
    try:
        final = follow(client, submission_id)
    except KeyboardInterrupt:
        flag = server_flag(client.server)
        render.stderr().print(
            f"\nstopped waiting; submission {submission_id} goes on on the server (not cancelled)\n"
            f"  follow it again: manieval status {submission_id} --wait{flag}\n"
            f"  cancel it:       manieval cancel {submission_id}{flag}"
        )
        raise typer.Exit(ExitCode.INTERRUPTED) from None
    if as_json:
        print_json(final)
    else:
        _report(final, client.server)
    raise typer.Exit(STATE_CODES[final["state"]])


def _report(s: dict[str, Any], server: str) -> None:
    """The result table; after a failure, where to read why (the reason was said already)."""
    out = render.stdout()
    if (shown := render.results(s)) is not None:
        out.print(shown)
    if s["state"] in ("failed", "timed_out", "error"):
        render.stderr().print(f"its log: manieval logs {s['id']}{server_flag(server)}")


def status(
    submission_id: Annotated[
        int | None,
        typer.Argument(min=1, help="A submission; without it, your recent ones are listed."),
    ] = None,
    challenge: Annotated[
        str | None, typer.Option(help="List only this challenge's submissions.")
    ] = None,
    limit: Annotated[int, typer.Option(min=1, max=200, help="How many to list.")] = 20,
    wait: Annotated[
        bool, typer.Option("--wait", help="Follow it to its end; exit 0 only if it succeeds.")
    ] = False,
    as_json: JsonOption = False,
    server: ServerOption = None,
) -> None:
    """Show one submission (state, timeline, results), or list your recent submissions."""
    if submission_id is None:
        if wait:
            raise typer.BadParameter("--wait needs a submission number", param_hint="--wait")
        _list_mine(server, challenge=challenge, limit=limit, as_json=as_json)
        return
    with handled(), connect(server, login="optional") as client:
        s = client.submission(submission_id)
        if wait:
            wait_and_report(client, submission_id, as_json=as_json)
    if as_json:
        print_json(s)
        return
    out = render.stdout()
    out.print(render.submission_summary(s))
    out.print(render.timeline(s))
    if (shown := render.results(s)) is not None:
        out.print(shown)
    if s["state"] not in FINAL_STATES:
        render.stderr().print(
            f"follow it: manieval status {s['id']} --wait{server_flag(client.server)}"
        )


def _list_mine(server: str | None, *, challenge: str | None, limit: int, as_json: bool) -> None:
    with handled(), connect(server, login="required") as client:
        items = client.my_submissions(challenge=challenge, per_page=limit)
    if as_json:
        print_json(items)
    elif not items:
        render.stderr().print("no submissions yet")
    else:
        render.stdout().print(render.submissions_table(items))


def logs(submission_id: SubmissionId, server: ServerOption = None) -> None:
    """Print the tail of your policy's log (stdout and stderr) for a submission."""
    with handled(), connect(server, login="required") as client:
        found = client.logs(submission_id)
        if not found["log_tail"]:
            state = client.submission(submission_id)["state"]
            render.stderr().print(empty_log_message(submission_id, found["attempt"], state))
            return
    text = render.printable(found["log_tail"], terminal=sys.stdout.isatty())
    sys.stdout.write(text if text.endswith("\n") else text + "\n")


def empty_log_message(submission_id: int, attempt: int, state: str) -> str:
    """What an empty log means in this state."""
    which = f"submission {submission_id} (attempt {attempt})"
    if state in FINAL_STATES:
        return f"{which} ended {state}; its policy wrote nothing to stdout or stderr"
    if state == "queued":
        return f"{which} has not started yet: no log"
    return f"no log for {which} yet: its policy has written nothing so far"


def trajectories(
    submission_id: SubmissionId,
    output: Annotated[
        Path, typer.Option("-o", "--output", help="The directory to write them to.")
    ] = Path("."),
    server: ServerOption = None,
) -> None:
    """Download a submission's trajectories in ManiSkill's format (.h5 + .json per task run)."""
    err = render.stderr()
    with handled(), connect(server, login="optional") as client:
        found = client.trajectories(submission_id)
        try:
            output.mkdir(parents=True, exist_ok=True)
            for t in found["trajectories"]:
                for url in (t["h5_url"], t["json_url"]):
                    name = url.rsplit("/", 1)[-1]
                    if not FILE_NAME.fullmatch(name):  # never a path the server chose
                        fail(ExitCode.SERVER_ERROR, f"the server named a file {name!r}")
                    size = client.download(url, output / name)
                    err.print(f"{output / name}: {size} bytes")
        except OSError as exc:
            fail(ExitCode.USAGE, f"cannot write to {output}: {exc}")
    replay = "python -m mani_skill.trajectory.replay_trajectory --traj-path"
    err.print(f"replay one: {replay} {output}/FILE.h5")


def cancel(submission_id: SubmissionId, server: ServerOption = None) -> None:
    """Cancel a queued or running submission (its quota is given back)."""
    with handled(), connect(server, login="required") as client:
        s = client.cancel(submission_id)
    render.stderr().print(Text(f"submission {s['id']}: ") + render.state(s["state"]))


def final(
    submission_id: SubmissionId,
    clear: Annotated[
        bool, typer.Option("--clear", help="Take the mark off: the phase's rule picks again.")
    ] = False,
    server: ServerOption = None,
) -> None:
    """Mark a submission as your final choice in its phase (where the phase's rules give one):
    it stands on the board once it succeeded; the mark moves from the one that had it."""
    with handled(), connect(server, login="required") as client:
        s = client.mark_final(submission_id, final=not clear)
    what = "is your final choice" if s["final"] else "is no longer your final choice"
    render.stderr().print(f"submission {s['id']} {what} in phase {s['phase']} of {s['challenge']}")


def post_deadline(
    challenge: Annotated[str, typer.Argument(help="The challenge's name.")],
    phase: Annotated[str, typer.Option(help="The phase.")] = "test",
    server: ServerOption = None,
    as_json: JsonOption = False,
) -> None:
    """Show a phase's post-deadline board: submissions made after it closed, ranked apart from
    the official board."""
    with handled(), connect(server, login="optional") as client:
        board = client.post_deadline(challenge, phase=phase)
    if as_json:
        print_json(board)
        return
    out = render.stdout()
    if not board["items"]:
        render.stderr().print(f"no post-deadline rows in phase {phase} of {challenge}")
    for row in board["items"]:
        rank = "-" if row["rank"] is None else str(row["rank"])
        out.print(f"{rank:>4}  {row['username']:<24} #{row['submission_id']:<8} {row['score']:.3f}")
