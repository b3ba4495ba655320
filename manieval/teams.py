"""Team commands: `manieval team show|create|invite|invitations|accept|decline|revoke|leave|
remove`. A user is in at most one team; in challenges with team mode on, its members share one
quota and one leaderboard row (docs/cli.md, Teams)."""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from manieval import render
from manieval.client import Client
from manieval.connect import JsonOption, ServerOption, connect, print_json
from manieval.errors import ExitCode, fail, handled

app = typer.Typer(
    help="Teams: create one, invite members, answer invitations, leave.",
    no_args_is_help=True,
    add_completion=False,
)
InvitationId = Annotated[int, typer.Argument(min=1, help="The invitation's number.")]
Username = Annotated[str, typer.Argument(help="A user name.")]


def _my_team_name(client: Client) -> str:
    team = client.my_team()["team"]
    if team is None:
        fail(ExitCode.CONFLICT, "you are not in a team", "create one: manieval team create NAME")
    name: str = team["name"]
    return name


def _team_table(team: dict[str, Any]) -> Table:
    table = Table(title=f"team {team['display_name']} ({team['name']})")
    for column in ("member", "role", "joined"):
        table.add_column(column)
    for member in team["members"]:
        role = "admin" if member["is_admin"] else "member"
        table.add_row(Text(member["username"]), role, render.local_time(member["joined_at"]))
    return table


def _invitations_table(items: list[dict[str, Any]], *, title: str, who: str) -> Table:
    table = Table(title=title)
    for column in ("id", who, "invited by", "sent"):
        table.add_column(column, justify="right" if column == "id" else "left")
    for item in items:
        name = (
            item["username"] if who == "user" else f"{item['team_display_name']} ({item['team']})"
        )
        table.add_row(
            str(item["id"]),
            Text(name),
            Text(item.get("invited_by") or "-"),
            render.local_time(item["created_at"]),
        )
    return table


@app.command("show")
def show(
    name: Annotated[str | None, typer.Argument(help="A team (default: yours).")] = None,
    as_json: JsonOption = False,
    server: ServerOption = None,
) -> None:
    """Show a team's members (yours by default; as its admin, with pending invitations)."""
    with handled(), connect(server, login="required" if name is None else "optional") as client:
        if name is None:
            mine = client.my_team()
            team, invitations = mine["team"], mine["invitations"]
        else:
            team, invitations = client.team(name), []
    if as_json:
        print_json(team)
        return
    out, err = render.stdout(), render.stderr()
    if team is None:
        err.print("you are not in a team: create one with manieval team create NAME")
    else:
        out.print(_team_table(team))
        if team.get("invitations"):
            out.print(
                _invitations_table(team["invitations"], title="pending invitations", who="user")
            )
    if invitations:
        err.print(
            f"{len(invitations)} invitation(s) wait for your answer: manieval team invitations"
        )


@app.command("create")
def create(
    name: Annotated[str, typer.Argument(help="3 to 32 of a-z, 0-9, '-' and '_'.")],
    display_name: Annotated[
        str | None,
        typer.Option("--display-name", help="As the leaderboard shows it (default: NAME)."),
    ] = None,
    server: ServerOption = None,
) -> None:
    """Create a team, with you as its admin."""
    with handled(), connect(server, login="required") as client:
        team = client.create_team(name=name, display_name=display_name or name)
    render.stderr().print(
        Text(f"team {team['name']} created; invite members with: ")
        + Text("manieval team invite USERNAME", style="bold")
    )


@app.command("invite")
def invite(username: Username, server: ServerOption = None) -> None:
    """Invite a user to your team (as its admin)."""
    with handled(), connect(server, login="required") as client:
        invitation = client.invite(team=_my_team_name(client), username=username)
    render.stderr().print(
        f"invited {invitation['username']} to {invitation['team']} (invitation "
        f"{invitation['id']}); they accept with: manieval team accept {invitation['id']}"
    )


@app.command("invitations")
def invitations(as_json: JsonOption = False, server: ServerOption = None) -> None:
    """List the invitations waiting for your answer."""
    with handled(), connect(server, login="required") as client:
        items = client.my_team()["invitations"]
    if as_json:
        print_json(items)
    elif not items:
        render.stderr().print("no invitations wait for your answer")
    else:
        render.stdout().print(_invitations_table(items, title="your invitations", who="team"))


@app.command("accept")
def accept(invitation_id: InvitationId, server: ServerOption = None) -> None:
    """Accept an invitation: join its team (leave yours first)."""
    with handled(), connect(server, login="required") as client:
        team = client.accept_invitation(invitation_id)
    render.stderr().print(f"you joined team {team['display_name']} ({team['name']})")


@app.command("decline")
def decline(invitation_id: InvitationId, server: ServerOption = None) -> None:
    """Decline an invitation."""
    with handled(), connect(server, login="required") as client:
        client.decline_invitation(invitation_id)
    render.stderr().print(f"invitation {invitation_id} declined")


@app.command("revoke")
def revoke(invitation_id: InvitationId, server: ServerOption = None) -> None:
    """Revoke a pending invitation of your team (as its admin)."""
    with handled(), connect(server, login="required") as client:
        client.revoke_invitation(team=_my_team_name(client), invitation_id=invitation_id)
    render.stderr().print(f"invitation {invitation_id} revoked")


@app.command("remove")
def remove(username: Username, server: ServerOption = None) -> None:
    """Remove a member from your team (as its admin)."""
    with handled(), connect(server, login="required") as client:
        team = _my_team_name(client)
        client.remove_member(team=team, username=username)
    render.stderr().print(f"{username} removed from team {team}")


@app.command("leave")
def leave(server: ServerOption = None) -> None:
    """Leave your team (its last member dissolves it)."""
    with handled(), connect(server, login="required") as client:
        left = client.leave_team()
    ending = "; it had no other member and is dissolved" if left["dissolved"] else ""
    render.stderr().print(f"you left team {left['team']}{ending}")
