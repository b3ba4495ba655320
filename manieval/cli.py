"""The `manieval` command: one entry point for participants, organizers and operators.

The participant commands and `evaluate` are light to import. The service's commands (`serve`,
`demo`, `db`, `admin`, `challenge`) and the in-pod `evaluate-job` import the server, SQLAlchemy,
the evaluator and the simulator: they are listed here by name and help line, and imported only
when one of them runs, so that `manieval --help` and every participant command answer at once
(bench/cli_startup.py measures it).
"""

from __future__ import annotations

import signal
import threading
from dataclasses import dataclass
from importlib import import_module
from typing import Any

import typer
from typer.core import TyperCommand, TyperGroup

from manieval import account, compare, participant, push, teams
from manieval.errors import ExitCode, not_installed
from manieval.evaluate import evaluate

PARTICIPATE = "Take part (against a server)"
OPERATE = "Evaluate locally and run the service"


@dataclass(frozen=True)
class Deferred:
    """A command imported when it runs: a Typer app, or a function made into a command."""

    module: str
    attribute: str
    help: str = ""
    hidden: bool = False

    def load(self, name: str) -> Any:
        """The real command (a Click command or group)."""
        try:
            found = getattr(import_module(self.module), self.attribute)
        except ModuleNotFoundError as exc:
            raise typer.Exit(not_installed(f"manieval {name}", exc)) from None
        if isinstance(found, typer.Typer):
            group = typer.main.get_group(found)
            group.name = name
            return group
        single = typer.Typer(add_completion=False)
        single.command(name, hidden=self.hidden, rich_help_panel=OPERATE)(found)
        return typer.main.get_command(single)


DEFERRED = {
    "evaluate-job": Deferred("evaluator.job", "evaluate_job", hidden=True),
    "serve": Deferred(
        "manieval.serve",
        "serve",
        "Run the service: the API and, on the embedded default, its worker (migrating the "
        "database first).",
    ),
    "demo": Deferred(
        "manieval.serve",
        "demo",
        "Run the service locally with the example policies evaluated on the leaderboard.",
    ),
    "db": Deferred("server.cli", "db_app", "Database schema."),
    "admin": Deferred("server.admin_cli", "admin_app", "Administrators and organizer tools."),
    "challenge": Deferred("server.cli", "challenge_app", "Challenges."),
}


class Placeholder(TyperCommand):
    """A deferred command's name and help line in `manieval --help`, until it runs."""

    def __init__(self, name: str, deferred: Deferred) -> None:
        super().__init__(name, help=deferred.help, hidden=deferred.hidden, rich_help_panel=OPERATE)
        self.deferred = deferred


class DeferringGroup(TyperGroup):
    """The top-level group: deferred commands are listed from `DEFERRED` and imported when
    they are resolved to run (or to show their own help)."""

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        for name, deferred in DEFERRED.items():
            self.commands.setdefault(name, Placeholder(name, deferred))

    def invoke(self, ctx: Any) -> Any:
        # Click's own answer to a Ctrl-C it did not expect is "Aborted!" and exit 1; ours is
        # the documented 130 (docs/cli.md), at any moment, a command's import included.
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            typer.echo("\ninterrupted", err=True)
            raise typer.Exit(ExitCode.INTERRUPTED) from None

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Any, list[str]]:
        name, command, rest = super().resolve_command(ctx, args)
        if isinstance(command, Placeholder) and name is not None:
            command = self.commands[name] = command.deferred.load(name)
        return name, command, rest


app = typer.Typer(
    name="manieval",
    help="ManiEval: evaluate manipulation policies on ManiSkill benchmark suites.",
    no_args_is_help=True,
    add_completion=False,
    cls=DeferringGroup,
)


@app.callback()
def main() -> None:
    """ManiEval command line."""
    stop_on_interrupt()


def stop_on_interrupt() -> None:
    """Ctrl-C (SIGINT) stops every command, however the command was started.

    A shell starts a background job (`manieval demo &`, a CI runner's step) with SIGINT
    ignored, and Python keeps an inherited "ignore". A SIGINT sent to `manieval` is meant for it,
    so the commands take it back, as uvicorn does: the demo and `serve` stop cleanly and
    `--wait` stops waiting, whoever started them and how.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)


for command in (
    account.register,
    account.login,
    account.logout,
    participant.challenges,
    participant.submit,
    push.push,
    participant.status,
    participant.logs,
    participant.trajectories,
    participant.cancel,
    participant.final,
    participant.leaderboard,
    compare.compare,
):
    app.command(rich_help_panel=PARTICIPATE)(command)
app.command("post-deadline", rich_help_panel=PARTICIPATE)(participant.post_deadline)
app.add_typer(teams.app, name="team", rich_help_panel=PARTICIPATE)

app.command("evaluate", rich_help_panel=OPERATE)(evaluate)
