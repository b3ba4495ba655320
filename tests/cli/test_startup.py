"""The command answers at once: help and the participant commands import neither the server,
the evaluator nor the simulator (bench/cli_startup.py measures the time; no timing here)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from manieval.cli import DEFERRED, app
from tests.cli.conftest import REPO

HEAVY = {"server", "evaluator", "worker", "sqlalchemy", "torch", "sapien", "mani_skill", "fastapi"}
HEAVY |= {"celery", "uvicorn", "numpy", "httpx"}

PROBE = """
import json, sys
from manieval.cli import app
try:
    app(sys.argv[1:], prog_name="manieval")
except SystemExit:
    pass
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
"""


def imported_by(*args: str) -> set[str]:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        check=True,
    )
    return set(json.loads(done.stdout.splitlines()[-1]))


@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["status", "--help"],
        ["submit", "--help"],
        ["evaluate", "--help"],
        ["compare", "--help"],
    ],
)
def test_help_imports_nothing_heavy(args: list[str]) -> None:
    assert imported_by(*args) & HEAVY == set()


def test_a_deferred_commands_help_line_is_its_own() -> None:
    for name, deferred in DEFERRED.items():
        loaded = deferred.load(name)
        assert loaded.name == name
        if not deferred.hidden:
            own = " ".join((loaded.help or "").split())
            assert own == deferred.help, name


def test_deferred_commands_are_listed_run_and_suggested() -> None:
    runner = CliRunner()
    listing = runner.invoke(app, ["--help"], env={"COLUMNS": "200"})
    assert listing.exit_code == 0
    for name in ("evaluate", "serve", "demo", "db", "admin", "challenge"):
        assert f" {name} " in listing.stdout
    assert "evaluate-job" not in listing.stdout
    db = runner.invoke(app, ["db", "--help"], env={"COLUMNS": "200"})
    assert db.exit_code == 0, db.output
    assert "upgrade" in db.stdout
    typo = runner.invoke(app, ["demoo"])
    assert typo.exit_code == 2
    assert "Did you mean 'demo'?" in typo.output


def test_a_deferred_command_whose_modules_are_missing_says_how_to_get_them(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from typer import Exit

    from manieval.cli import Deferred

    with pytest.raises(Exit) as stopped:
        Deferred("manieval.not_in_the_slim_cli", "serve").load("serve")
    assert stopped.value.exit_code == 2
    said = capsys.readouterr().err
    assert "manieval serve cannot run here (no module manieval.not_in_the_slim_cli)" in said
    assert "make install" in said
