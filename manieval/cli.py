"""The `manieval` command: one entry point for participants, organizers and operators."""

import typer

from evaluator.job import evaluate_job
from manieval import account, participant, push
from manieval.evaluate import evaluate
from manieval.serve import demo, serve
from server.cli import admin_app, challenge_app, db_app

app = typer.Typer(
    name="manieval",
    help="ManiEval: evaluate manipulation policies on ManiSkill benchmark suites.",
    no_args_is_help=True,
    add_completion=False,
)

PARTICIPATE = "Take part (against a server)"
OPERATE = "Evaluate locally and run the service"


@app.callback()
def main() -> None:
    """ManiEval command line."""


for command in (
    account.register,
    account.login,
    account.logout,
    participant.challenges,
    participant.submit,
    push.push,
    participant.status,
    participant.logs,
    participant.cancel,
    participant.leaderboard,
):
    app.command(rich_help_panel=PARTICIPATE)(command)

app.command("evaluate", rich_help_panel=OPERATE)(evaluate)
app.command("evaluate-job", hidden=True)(evaluate_job)
app.command("serve", rich_help_panel=OPERATE)(serve)
app.command("demo", rich_help_panel=OPERATE)(demo)
app.add_typer(db_app, name="db", rich_help_panel=OPERATE)
app.add_typer(admin_app, name="admin", rich_help_panel=OPERATE)
app.add_typer(challenge_app, name="challenge", rich_help_panel=OPERATE)
