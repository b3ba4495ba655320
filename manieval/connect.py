"""Which server a participant command talks to, and with which token.

The server: --server (or MANIEVAL_SERVER), else the one of the saved login, else the local
default. The token: MANIEVAL_TOKEN, else the saved one when it belongs to that server: a token
is never sent to another server.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Annotated, Literal

import typer

from manieval import credentials
from manieval.client import DEFAULT_SERVER, Client, NotLoggedIn, normalise_server
from manieval.credentials import Credentials, CredentialsError

SERVER_ENV = "MANIEVAL_SERVER"
TOKEN_ENV = "MANIEVAL_TOKEN"

ServerOption = Annotated[
    str | None,
    typer.Option(
        "--server",
        envvar=SERVER_ENV,
        show_default=False,
        help=f"The server's URL (default: the one you logged in to, else {DEFAULT_SERVER}).",
    ),
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print JSON, for programs.")]


def print_json(data: object) -> None:
    """Data for programs, on stdout."""
    sys.stdout.write(json.dumps(data, indent=2) + "\n")


def saved_login() -> Credentials | None:
    """The saved login, or None (also when its file is unreadable)."""
    try:
        return credentials.load()
    except CredentialsError:
        return None


def resolve_server(option: str | None) -> str:
    """--server (or MANIEVAL_SERVER), else the server of the saved login, else the default."""
    if option:
        try:
            return normalise_server(option)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--server") from None
    saved = saved_login()
    return saved.server if saved is not None else DEFAULT_SERVER


def connect(option: str | None, *, login: Literal["required", "optional", "none"]) -> Client:
    """A client of the chosen server, with MANIEVAL_TOKEN or the saved token when it is for
    that server (a token is never sent to another one)."""
    server = resolve_server(option)
    if login == "none":
        return Client(server)
    token = os.environ.get(TOKEN_ENV) or None
    if token is None:
        try:
            saved = credentials.load()
        except CredentialsError:
            if login == "required":
                raise
            saved = None
        if saved is not None and saved.server == server:
            token = saved.token
        elif login == "required":
            raise NotLoggedIn(server, other=saved.server if saved is not None else None)
    return Client(server, token=token)
