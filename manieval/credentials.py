"""The saved login: one API token and the server it belongs to.

It lives in ``credentials.json`` under ``platformdirs.user_config_dir("manieval")`` (or
``MANIEVAL_CONFIG_DIR``), in a 0700 directory, mode 0600, replaced atomically so that a reader
never sees half a file and the token is never readable by others, not even for an instant.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import platformdirs

CONFIG_DIR_ENV = "MANIEVAL_CONFIG_DIR"
FILE_NAME = "credentials.json"


class CredentialsError(Exception):
    """The file exists but cannot be used."""


@dataclass(frozen=True)
class Credentials:
    server: str
    username: str
    token: str
    token_id: int
    token_name: str


def config_dir() -> Path:
    override = os.environ.get(CONFIG_DIR_ENV)
    return Path(override) if override else Path(platformdirs.user_config_dir("manieval"))


def credentials_path() -> Path:
    return config_dir() / FILE_NAME


def load() -> Credentials | None:
    """The saved login, or None when there is none."""
    path = credentials_path()
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return Credentials(
            server=str(data["server"]),
            username=str(data["username"]),
            token=str(data["token"]),
            token_id=int(data["token_id"]),
            token_name=str(data.get("token_name", "")),
        )
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CredentialsError(f"{path} cannot be read ({exc})") from None


def save(credentials: Credentials) -> Path:
    """Write the login atomically, mode 0600 from its creation, in a 0700 directory."""
    directory = config_dir()
    # A directory the user named and made is left as it is; ours is made 0700.
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    path = directory / FILE_NAME
    fd, temporary = tempfile.mkstemp(dir=directory, prefix=".credentials-", suffix=".tmp")
    try:
        # mkstemp creates the file 0600: the token is never readable by anyone else.
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            json.dump(asdict(credentials), out, indent=2)
            out.write("\n")
            out.flush()
            os.fsync(out.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def delete() -> bool:
    """Remove the saved login; False if there was none."""
    try:
        credentials_path().unlink()
    except FileNotFoundError:
        return False
    return True
