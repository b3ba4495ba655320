"""`python -m manieval` and the `manieval` command."""

import sys

INTERRUPTED = 130  # manieval.errors.ExitCode.INTERRUPTED, without importing anything yet


def main() -> None:
    """Run `manieval`: a Ctrl-C while it still loads ends it as a Ctrl-C at work does (130)."""
    try:
        from manieval.cli import app
    except KeyboardInterrupt:
        sys.exit(INTERRUPTED)
    app(prog_name="manieval")


if __name__ == "__main__":
    main()
