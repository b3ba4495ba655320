"""The mails of accounts: what they say (`Letters`, pure) and `send_after`, which hands a
message to the mailer once the request's transaction has committed and its answer has gone.
So a mail is never sent for a change that was rolled back, and neither a slow mail server nor
the time sending takes tells a caller whether an address has an account.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from datetime import timedelta
from email.message import EmailMessage
from email.utils import formatdate, make_msgid, parseaddr
from typing import Any
from urllib.parse import quote, urlencode

from fastapi import BackgroundTasks, Request

from server.kit.mailer import Mailer, mailer_for
from server.kit.settings import Settings

log = logging.getLogger(__name__)
SITE = "ManiEval"
VERIFY_PATH = "/verify"
RESET_PATH = "/reset-password"
FORGOT_PATH = "/forgot-password"


def duration(span: timedelta) -> str:
    """A link's lifetime in words: "48 hours", "1 hour", "90 minutes"."""
    minutes = int(span.total_seconds() // 60)
    if minutes % 60 == 0:
        hours = minutes // 60
        return "1 hour" if hours == 1 else f"{hours} hours"
    return f"{minutes} minutes"


@dataclass(frozen=True)
class Letters:
    """What the service's mails say, where their links lead and how long those links work."""

    sender: str
    base_url: str
    verify_for: timedelta
    reset_for: timedelta

    def verification(self, *, username: str, email: str, token: str, change: bool) -> EmailMessage:
        """The link that proves `email` is `username`'s (a new address, when `change`)."""
        why = (
            f"You asked to use this address for your {SITE} account '{username}'. "
            "Your account keeps its old address until you follow this link:"
            if change
            else f"Welcome to {SITE}, {username}. Confirm that this address is yours:"
        )
        body = (
            f"{why}\n\n{self._link(VERIFY_PATH, token)}\n\n"
            f"The link works once, for {duration(self.verify_for)}. The page it opens asks you "
            "to confirm with a button.\n\n"
            f"If you did not ask for this, ignore this mail: nothing changes.\n"
        )
        return self._message(to=email, subject=f"Confirm your email address for {SITE}", body=body)

    def password_reset(self, *, username: str, email: str, token: str) -> EmailMessage:
        """The link that sets a new password for `username`."""
        body = (
            f"Someone asked to reset the password of the {SITE} account '{username}', which "
            "uses this address. To choose a new password, open this link:\n\n"
            f"{self._link(RESET_PATH, token)}\n\n"
            f"The link works once, for {duration(self.reset_for)}. Setting a new password logs "
            "the account out everywhere.\n\n"
            "If it was not you, ignore this mail: your password stays as it is.\n"
        )
        return self._message(to=email, subject=f"Reset your {SITE} password", body=body)

    def address_in_use(self, *, email: str) -> EmailMessage:
        """To an address another account asked to move to: it has an account already."""
        body = (
            f"Someone asked to use this address for a {SITE} account, but it already belongs "
            "to an account, so nothing changed.\n\n"
            "If that account is yours and you forgot its password, choose a new one here:\n\n"
            f"{self.base_url}{FORGOT_PATH}\n\n"
            "Otherwise, ignore this mail.\n"
        )
        return self._message(
            to=email, subject=f"This address already has a {SITE} account", body=body
        )

    def _link(self, path: str, token: str) -> str:
        return f"{self.base_url}{path}?{urlencode({'token': token})}"

    def _message(self, *, to: str, subject: str, body: str) -> EmailMessage:
        message = EmailMessage()
        message["From"] = self.sender
        message["To"] = to
        message["Subject"] = subject
        message["Date"] = formatdate(usegmt=True)
        # The sender's domain, not the host's name: finding that may wait on DNS.
        domain = parseaddr(self.sender)[1].rpartition("@")[2] or "localhost"
        message["Message-ID"] = make_msgid(domain=domain)
        message["Auto-Submitted"] = "auto-generated"  # RFC 3834: no vacation replies to it
        # 7bit: the text is ASCII, so the .eml file reads as it is and its links stay whole
        # (quoted-printable would break a long link and turn its '=' into '=3D').
        message.set_content(body, cte="7bit")
        return message


def letters_for(settings: Settings, request: Request) -> Letters:
    """The letters of this server; links start with `public_url`, else this request's address."""
    # The request's address comes from its Host header; percent-encoding keeps it ASCII.
    base = settings.public_url or quote(str(request.base_url), safe=":/?#[]@!$&'()*+,;=%")
    return Letters(
        sender=settings.mail_from,
        base_url=base.rstrip("/"),
        verify_for=timedelta(hours=settings.verify_link_hours),
        reset_for=timedelta(minutes=settings.reset_link_minutes),
    )


def deliver(mailer: Mailer, message: EmailMessage) -> None:
    """Send `message`; a failure is logged, and the person can ask again (rate-limited)."""
    try:
        mailer.send(message)
    except OSError as exc:  # smtplib's errors, refused connections and TLS failures all are
        log.warning("could not send mail to %s: %s", message["To"], exc)


def send_after(tasks: BackgroundTasks, settings: Settings, message: EmailMessage | None) -> None:
    """Send `message` once the answer has gone (the caller has committed); None: nothing."""
    if message is not None:
        tasks.add_task(deliver, mailer_for(settings), message)


@asynccontextmanager
async def announce_mail(app: Any) -> AsyncIterator[None]:
    """At start-up, say where mail goes (on the embedded default: the folder to look in)."""
    settings: Settings = app.state.services.settings
    log.info("%s", mailer_for(settings).describe())
    yield
