"""The `manieval` command: one entry point for participants, organizers and operators."""

import typer

from evaluator.cli import evaluate

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
