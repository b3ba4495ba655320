"""How the suite starts processes: as from a terminal, whatever started pytest (issue 25)."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from tests.cli.conftest import ignore_sigint

REPO = Path(__file__).resolve().parents[1]
DISPOSITIONS = (
    "import signal; print(signal.getsignal(signal.SIGINT) is signal.default_int_handler,"
    " signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)"
)


def test_a_process_a_test_starts_has_sigint_and_sigterm_at_their_defaults() -> None:
    done = subprocess.run(
        [sys.executable, "-c", DISPOSITIONS], capture_output=True, text=True, timeout=60
    )
    assert done.stdout.split() == ["True", "True"], done.stderr


def test_pytest_started_with_sigint_ignored_still_starts_its_children_as_a_terminal_would(
    tmp_path: Path,
) -> None:
    """The test above, in a pytest started as `nohup make test &` starts it."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-p",
            "no:cacheprovider",
            "-q",
            f"--basetemp={tmp_path / 'inner'}",
            f"{Path(__file__)}::{test_a_process_a_test_starts_has_sigint_and_sigterm_at_their_defaults.__name__}",
        ],
        cwd=REPO,
        preexec_fn=ignore_sigint,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "1 passed" in done.stdout


def test_an_ignored_sigint_is_what_the_background_start_really_passes_on() -> None:
    """The premise of the test above: without the suite's reset, a child would keep it."""
    done = subprocess.run(
        [sys.executable, "-c", "import signal; print(signal.getsignal(signal.SIGINT))"],
        preexec_fn=ignore_sigint,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.stdout.strip() == str(int(signal.SIG_IGN)), done.stderr
