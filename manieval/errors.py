"""How the participant commands fail: a message a person understands and an exit code each.

The codes are documented in docs/cli.md; scripts rely on them, so they never change meaning.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from enum import IntEnum
from typing import NoReturn

import typer
from rich.text import Text

from manieval import credentials, render
from manieval.client import DEFAULT_SERVER, ApiError, NotLoggedIn, Unreachable, speaks_api
from manieval.credentials import CredentialsError


class ExitCode(IntEnum):
    OK = 0  # done; with --wait: the submission succeeded
    FAILED = 1  # the submission ended `failed` (the policy's fault)
    USAGE = 2  # bad command line (also what Typer itself exits with)
    TIMED_OUT = 3  # the submission ended `timed_out`
    EVALUATION_ERROR = 4  # the submission ended `error` (the service's fault)
    CANCELLED = 5  # the submission ended `cancelled`
    UNREACHABLE = 10  # no answer from the server
    BAD_CREDENTIALS = 11  # wrong username, email or password
    NOT_LOGGED_IN = 12  # no saved login for this server
    TOKEN_REJECTED = 13  # the saved token was revoked or expired
    QUOTA_EXCEEDED = 14
    RATE_LIMITED = 15
    INVALID = 16  # the server refused a value (image reference, phase, password...)
    NOT_FOUND = 17  # unknown challenge or submission (or not yours to see)
    CONFLICT = 18  # e.g. cancelling an ended submission, a closed phase, a taken username
    FORBIDDEN = 19
    SERVER_ERROR = 20  # the server failed (5xx) or does not speak the ManiEval API
    NO_ENGINE = 21  # push: neither Podman nor Docker is installed here
    IMAGE_NOT_FOUND = 22  # push: the local engine has no such image
    PUSH_REFUSED = 23  # push: the registry refused the login or the upload (namespace, size)
    REGISTRY_UNREACHABLE = 24  # push: no answer from the registry
    INTERRUPTED = 130  # Ctrl-C


STATE_CODES = {
    "succeeded": ExitCode.OK,
    "failed": ExitCode.FAILED,
    "timed_out": ExitCode.TIMED_OUT,
    "error": ExitCode.EVALUATION_ERROR,
    "cancelled": ExitCode.CANCELLED,
}


def server_flag(server: str) -> str:
    """What a suggested command needs to reach `server`: nothing when it is the default."""
    try:
        saved = credentials.load()
    except CredentialsError:
        saved = None
    default = saved.server if saved is not None else DEFAULT_SERVER
    return "" if server in ("", default) else f" --server {server}"


def fail(code: ExitCode, message: str, *details: str) -> NoReturn:
    """Print `error: message` and the details on stderr, and exit with `code`."""
    err = render.stderr()
    err.print(Text("error: ", style="bold red") + Text(message))
    for line in details:
        err.print(Text(f"  {line}"))
    raise typer.Exit(int(code))


@contextmanager
def handled() -> Iterator[None]:
    """Turn every client failure inside into its message and exit code (no traceback)."""
    try:
        yield
    except Unreachable as exc:
        fail(
            ExitCode.UNREACHABLE,
            f"cannot reach the ManiEval server at {exc.server} ({exc.reason})",
            "is it running? Name another server with --server URL or MANIEVAL_SERVER.",
        )
    except NotLoggedIn as exc:
        details = [f"run: manieval login{server_flag(exc.server)}"]
        if exc.other is not None:
            details.insert(0, f"(your saved login is for {exc.other})")
        fail(ExitCode.NOT_LOGGED_IN, f"not logged in to {exc.server}", *details)
    except CredentialsError as exc:
        fail(ExitCode.NOT_LOGGED_IN, f"the saved login is unusable: {exc}", "run: manieval login")
    except ApiError as exc:
        explain(exc)


def explain(exc: ApiError) -> NoReturn:
    """The server's refusal, in words and an exit code."""
    fields = [f"{name}: {problem}" for name, problem in exc.fields.items()]
    message = exc.message
    if len(exc.fields) == 1 and exc.message in exc.fields.values():
        # One field, and the message is its problem: name the field once.
        message, fields = f"invalid {fields[0]}", []
    if exc.code in ("http_error", "not_json"):
        fail(ExitCode.SERVER_ERROR, exc.message, "is --server the address of a ManiEval server?")
    if exc.status == 404 and exc.server and not speaks_api(exc.server):
        # Our own server under a wrong path prefix answers 404 to everything: not a "no such
        # challenge", but a URL that is not the API's.
        fail(
            ExitCode.SERVER_ERROR,
            f"{exc.server} does not answer as a ManiEval server ({exc.message})",
            "is --server the address of a ManiEval server (with its path prefix, if any)?",
        )
    if exc.status == 401:
        if exc.authenticated:
            fail(
                ExitCode.TOKEN_REJECTED,
                f"the server refused your API token ({exc.message})",
                f"it was revoked or has expired: run manieval login{server_flag(exc.server)}",
            )
        fail(
            ExitCode.NOT_LOGGED_IN,
            f"this needs a login ({exc.message})",
            f"run: manieval login{server_flag(exc.server)}",
        )
    if exc.code == "quota_exceeded":
        quota_exceeded(exc)
    if exc.status == 429:
        wait = f"try again in {render.duration(exc.retry_after)}" if exc.retry_after else ""
        fail(ExitCode.RATE_LIMITED, f"rate limited: {exc.message}", *filter(None, [wait]))
    if exc.status >= 500:
        fail(
            ExitCode.SERVER_ERROR,
            f"the server failed (HTTP {exc.status}): {exc.message}",
            *fields,
            "try again later; if it goes on, tell the challenge's organizers",
        )
    by_status = {
        400: ExitCode.INVALID,
        403: ExitCode.FORBIDDEN,
        404: ExitCode.NOT_FOUND,
        409: ExitCode.CONFLICT,
        422: ExitCode.INVALID,
    }
    fail(by_status.get(exc.status, ExitCode.SERVER_ERROR), message, *fields)


def quota_exceeded(exc: ApiError) -> NoReturn:
    if exc.resets_at is None:  # the concurrent limit: it frees up when a run ends
        wait = f"try again in {render.duration(exc.retry_after)}" if exc.retry_after else ""
        fail(ExitCode.QUOTA_EXCEEDED, f"quota exceeded: {exc.message}", *filter(None, [wait]))
    # The server's message names the time in UTC; say it in the user's own time instead.
    what = exc.message.split(";", 1)[0]
    left = (exc.resets_at - datetime.now(UTC)).total_seconds()
    fail(
        ExitCode.QUOTA_EXCEEDED,
        f"quota exceeded: {what}",
        f"the next submission is possible at {render.local_time(exc.resets_at)}"
        f" (in {render.duration(left)})",
    )


FULL_INSTALL = (
    "it is part of the whole of ManiEval (the server, the worker and the simulator), which the "
    "participant's `manieval-cli` leaves out: install ManiEval from its repository "
    "(`make install`) to run it"
)


def not_installed(command: str, exc: ModuleNotFoundError) -> ExitCode:
    """Say that `command` needs the whole of ManiEval (`exc`: the module missing)."""
    typer.echo(f"error: {command} cannot run here (no module {exc.name}): {FULL_INSTALL}", err=True)
    return ExitCode.USAGE
