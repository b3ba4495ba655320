"""The `manieval` command: one entry point for participants, organizers and operators."""

import typer

from evaluator.cli import evaluate
from evaluator.job import evaluate_job
from server.cli import admin_app, challenge_app, db_app, demo, serve

app = typer.Typer(
    name="manieval",
    help="ManiEval: evaluate manipulation policies on ManiSkill benchmark suites.",
    no_args_is_help=True,
    add_completion=False,
)


@app.callback()
def main() -> None:
    """ManiEval command line."""


app.command("evaluate")(evaluate)
app.command("evaluate-job", hidden=True)(evaluate_job)
app.command("serve")(serve)
app.command("demo")(demo)
app.add_typer(db_app, name="db")
app.add_typer(admin_app, name="admin")
app.add_typer(challenge_app, name="challenge")
