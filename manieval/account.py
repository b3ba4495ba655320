"""Account commands: register, login (an API token saved for the other commands), logout."""

from __future__ import annotations

import socket
import sys
from typing import Annotated

import typer
from rich.text import Text

from manieval import credentials, render
from manieval.client import ApiError, Client, Unreachable, is_loopback
from manieval.connect import ServerOption, connect, resolve_server, saved_login
from manieval.credentials import Credentials, CredentialsError
from manieval.engine_login import login_engine_after
from manieval.errors import ExitCode, fail, handled, server_flag

PasswordStdin = Annotated[
    bool,
    typer.Option("--password-stdin", help="Read the password from the first line of stdin."),
]


def _password(from_stdin: bool, *, confirm: bool) -> str:
    if from_stdin:
        password = sys.stdin.readline().rstrip("\r\n")
        if not password:
            raise typer.BadParameter("no password on stdin", param_hint="--password-stdin")
        return password
    value: str = typer.prompt("password", hide_input=True, confirmation_prompt=confirm)
    return value


def register(
    username: Annotated[
        str, typer.Option("--username", "-u", prompt=True, help="3 to 32 of a-z, 0-9, _ and -.")
    ],
    email: Annotated[str, typer.Option("--email", prompt=True)],
    password_stdin: PasswordStdin = False,
    server: ServerOption = None,
) -> None:
    """Create an account (the password is asked twice, hidden)."""
    password = _password(password_stdin, confirm=True)
    with handled(), connect(server, login="none") as client:
        client.register(username=username, email=email, password=password)
    render.stderr().print(
        Text(f"account {username} created on {client.server}; log in with: ")
        + Text(f"manieval login -u {username}{server_flag(client.server)}", style="bold")
    )


def login(
    username: Annotated[
        str, typer.Option("--username", "-u", prompt="username or email", help="Username or email.")
    ],
    password_stdin: PasswordStdin = False,
    token_name: Annotated[
        str | None,
        typer.Option(
            help="Name of the API token (default: manieval-cli@HOSTNAME).", show_default=False
        ),
    ] = None,
    server: ServerOption = None,
) -> None:
    """Log in: create an API token and save it (mode 0600) for the other commands."""
    url = resolve_server(server)
    err = render.stderr()
    if not url.startswith("https://") and not is_loopback(url):
        err.print(Text(f"warning: {url} is not https: the password travels unencrypted", "yellow"))
    password = _password(password_stdin, confirm=False)
    name = (token_name or f"manieval-cli@{socket.gethostname()}")[:64]
    with handled(), Client(url) as client:
        try:
            new = client.create_token(login=username, password=password, name=name)
        except ApiError as exc:
            if exc.status == 401:
                fail(ExitCode.BAD_CREDENTIALS, "wrong username, email or password", f"on {url}")
            raise
        with Client(url, token=new["token"]) as authenticated:
            me = authenticated.me()["user"]
    previous = saved_login()
    saved = Credentials(
        server=url,
        username=me["username"],
        token=new["token"],
        token_id=new["id"],
        token_name=new["name"],
    )
    try:
        path = credentials.save(saved)
    except OSError as exc:  # a token saved nowhere must not stay valid on the server
        _revoke(saved)
        fail(
            ExitCode.NOT_LOGGED_IN,
            f"cannot save the API token: {exc}",
            "the token was revoked again; set MANIEVAL_CONFIG_DIR to a writable directory",
        )
    except BaseException:
        _revoke(saved)
        raise
    err.print(f"logged in to {url} as {saved.username}; token saved in {path}")
    with Client(url, token=saved.token) as authenticated:
        login_engine_after(authenticated, username=saved.username)
    if previous is not None and (previous.server, previous.token_id) != (url, saved.token_id):
        _forget(previous)


def _forget(previous: Credentials) -> None:
    """The replaced token is no longer saved anywhere: revoke it rather than leave it valid."""
    if (problem := _revoke(previous)) is not None:
        render.stderr().print(
            Text(
                f"the previous token {previous.token_name!r} on {previous.server} is still "
                f"valid: {problem}",
                style="yellow",
            )
        )


def _revoke(saved: Credentials) -> str | None:
    """Revoke the saved token on its server; None when done, else why not."""
    try:
        with Client(saved.server, token=saved.token) as client:
            client.revoke_token(saved.token_id)
    except Unreachable as exc:
        return f"the server could not be reached ({exc.reason})"
    except ApiError as exc:
        if exc.status == 401:
            return None  # already revoked
        return f"the server refused ({exc.message})"
    return None


def logout(server: ServerOption = None) -> None:
    """Revoke the saved API token on the server and delete it here (even if the server is gone)."""
    err = render.stderr()
    try:
        saved = credentials.load()
    except CredentialsError as exc:
        credentials.delete()
        err.print(f"removed an unreadable login file ({exc})")
        return
    if saved is None:
        err.print("not logged in")
        return
    if server and resolve_server(server) != saved.server:
        fail(
            ExitCode.NOT_LOGGED_IN,
            f"not logged in to {resolve_server(server)}",
            f"(your saved login is for {saved.server})",
        )
    problem = _revoke(saved)
    credentials.delete()
    if problem is None:
        err.print(f"logged out of {saved.server}: token {saved.token_name!r} revoked and deleted")
        return
    err.print(
        Text(
            f"logged out here: the token file is deleted, but {problem}, so token "
            f"{saved.token_name!r} is still valid on {saved.server}; revoke it on your account "
            "page when the server is back",
            style="yellow",
        )
    )
