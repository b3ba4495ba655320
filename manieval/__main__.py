"""`python -m manieval`: the same as the `manieval` command."""

from manieval.cli import app

app(prog_name="manieval")
