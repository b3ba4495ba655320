"""How mail leaves the server: `SmtpMailer` through an SMTP server (STARTTLS, TLS from the
start, or plain on the loopback address; with credentials), or `FolderMailer`, the embedded
default, which writes each message as an RFC 5322 ``.eml`` file so that a laptop install
needs no mail server. `mailer_for(settings)` picks the one the settings name.

Sending is I/O that may be slow or fail: callers send after their transaction has committed,
never inside it (server/accounts/mail.py).
"""

from __future__ import annotations

import logging
import os
import secrets
import smtplib
import ssl
from dataclasses import dataclass, field
from datetime import UTC, datetime
from email import policy
from email.message import EmailMessage
from pathlib import Path
from typing import Literal, Protocol

from pydantic import SecretStr

from server.kit.settings import Settings

log = logging.getLogger(__name__)


class Mailer(Protocol):
    def send(self, message: EmailMessage) -> None:
        """Deliver `message` to its `To` address, or raise (OSError, smtplib.SMTPException)."""

    def describe(self) -> str:
        """Where mail goes, in words, for the server's start-up log line."""


@dataclass(frozen=True)
class SmtpMailer:
    """One SMTP conversation per message (mail is rare: a registration, a reset)."""

    host: str
    port: int
    security: Literal["starttls", "ssl", "none"] = "starttls"
    username: str | None = None
    password: SecretStr | None = field(default=None, repr=False)
    ca_file: Path | None = None
    timeout: float = 10.0

    def send(self, message: EmailMessage) -> None:
        context = ssl.create_default_context(cafile=self.ca_file)
        smtp: smtplib.SMTP
        if self.security == "ssl":
            smtp = smtplib.SMTP_SSL(self.host, self.port, timeout=self.timeout, context=context)
        else:
            smtp = smtplib.SMTP(self.host, self.port, timeout=self.timeout)
        with smtp:
            if self.security == "starttls":
                # Raises when the server offers no STARTTLS: never fall back to plain text.
                smtp.starttls(context=context)
            if self.username is not None and self.password is not None:
                smtp.login(self.username, self.password.get_secret_value())
            smtp.send_message(message)

    def describe(self) -> str:
        return f"mail is sent through SMTP at {self.host}:{self.port} ({self.security})"


@dataclass(frozen=True)
class FolderMailer:
    """Each message as a file `<time>-<random>.eml` in `folder`, readable only by its owner
    (a mail may hold a password-reset link). Any mail program opens it."""

    folder: Path

    def send(self, message: EmailMessage) -> None:
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
        path = self.folder / f"{stamp}-{secrets.token_hex(4)}.eml"
        tmp = path.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(message.as_bytes(policy=policy.SMTP))
        os.replace(tmp, path)  # a reader never sees half a message
        log.info("mail to %s written to %s", message["To"], path)

    def describe(self) -> str:
        return f"mail is written to {self.folder} (one .eml file per message, no mail server)"


def mailer_for(settings: Settings) -> Mailer:
    """The mailer the settings name: SMTP, or the folder `<data_dir>/mail`."""
    if settings.mail_backend == "smtp":
        return SmtpMailer(
            host=settings.smtp_host,
            port=settings.smtp_port,
            security=settings.smtp_security,
            username=settings.smtp_username,
            password=settings.smtp_password,
            ca_file=settings.smtp_ca_file,
            timeout=settings.smtp_timeout,
        )
    return FolderMailer(settings.data_dir / "mail")
