"""Email: verification on registration, password reset and email change, through a real SMTP
server (aiosmtpd on 127.0.0.1); the folder mailer of the embedded default; the submit check.

Every link is single-use and expiring, stored only as its SHA-256, and no answer tells
whether an address has an account.
"""

from __future__ import annotations

import hashlib
import ipaddress
import logging
import re
import socket
import ssl
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from email import message_from_bytes, policy
from email.message import EmailMessage
from pathlib import Path
from typing import Any

import pytest
from aiosmtpd.controller import Controller
from aiosmtpd.smtp import AuthResult, LoginPassword
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from fastapi.testclient import TestClient
from pydantic import SecretStr, ValidationError
from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from server.accounts import verification
from server.accounts.mail import Letters
from server.app import create_app
from server.kit.errors import Invalid
from server.kit.mailer import FolderMailer, SmtpMailer
from server.kit.ratelimit import MemoryRateLimiter
from server.kit.settings import Settings
from server.models import User
from server.models.accounts import EmailToken
from testkit.factories import (
    PASSWORD,
    RecordingQueue,
    fake_resolve_for,
    make_challenge,
    make_user,
    token_for,
)

API = "/api/v1"
IMAGE = "127.0.0.1:5000/team/policy:v1"
NEW_PASSWORD = "purple submarine orchestra lantern"
TOKEN = re.compile(r"[?&]token=([A-Za-z0-9_-]{43})")
WAIT_S = 60.0  # a busy machine: bounded by progress, not a timing assert


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Inbox:
    """What the SMTP server received, in order; a handler of aiosmtpd's."""

    messages: list[EmailMessage] = field(default_factory=list)
    envelopes: list[tuple[str, list[str]]] = field(default_factory=list)
    logins: list[str] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    async def handle_DATA(self, server: Any, session: Any, envelope: Any) -> str:
        message = message_from_bytes(envelope.original_content, policy=policy.default)
        assert isinstance(message, EmailMessage)
        with self.changed:
            self.messages.append(message)
            self.envelopes.append((envelope.mail_from, list(envelope.rcpt_tos)))
            self.changed.notify_all()
        return "250 OK"

    def wait(self, count: int) -> list[EmailMessage]:
        with self.changed:
            arrived = self.changed.wait_for(lambda: len(self.messages) >= count, WAIT_S)
            assert arrived, f"{len(self.messages)} of {count} mails arrived"
            return list(self.messages)

    def clear(self) -> None:
        with self.changed:
            self.messages.clear()
            self.envelopes.clear()
            self.logins.clear()


def body_of(message: EmailMessage) -> str:
    part = message.get_body(("plain",))
    assert part is not None
    return str(part.get_content())  # type: ignore[attr-defined]


def token_in(message: EmailMessage) -> str:
    found = TOKEN.search(body_of(message))
    assert found, body_of(message)
    return found.group(1)


@pytest.fixture(scope="module")
def smtp_server() -> Iterator[tuple[Inbox, int]]:
    inbox = Inbox()
    port = free_port()
    controller = Controller(inbox, hostname="127.0.0.1", port=port)
    controller.start()
    try:
        yield inbox, port
    finally:
        controller.stop()


@pytest.fixture
def inbox(smtp_server: tuple[Inbox, int]) -> Inbox:
    smtp_server[0].clear()
    return smtp_server[0]


@pytest.fixture
def settings(tmp_path: Path, smtp_server: tuple[Inbox, int]) -> Settings:
    """The shared test settings, with mail through the SMTP server and verification required."""
    return Settings(
        dev_mode=True,
        data_dir=tmp_path,
        cookie_secure=False,
        register_rate="1000/minute",
        login_rate="1000/minute",
        token_rate="1000/minute",
        submit_rate="1000/minute",
        mail_rate="1000/minute",
        mail_backend="smtp",
        smtp_host="127.0.0.1",
        smtp_port=smtp_server[1],
        smtp_security="none",
        public_url="https://manieval.example.org",
        require_verified_email=True,
    )


def register(client: TestClient, username: str) -> TestClient:
    """Register by the API; returns `client` logged in with a cookie."""
    body = {"username": username, "email": f"{username}@example.org", "password": PASSWORD}
    r = client.post(f"{API}/users", json=body)
    assert r.status_code == 201, r.text
    assert r.json()["email_verified"] is False
    return client


def submit(client: TestClient, headers: dict[str, str]) -> Any:
    body = {"challenge": "server-tiny", "phase": "dev", "image": IMAGE}
    return client.post(f"{API}/submissions", json=body, headers=headers)


def tokens_of(db: Session, username: str) -> list[EmailToken]:
    user = db.scalar(select(User).where(User.username == username))
    assert user is not None
    db.expire_all()
    return list(db.scalars(select(EmailToken).where(EmailToken.user_id == user.id)))


# Verification --------------------------------------------------------------------------------


def test_registration_mails_a_link_that_verifies_the_address_and_then_allows_submitting(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_challenge(db)
    register(client, "alice")
    [mail] = inbox.wait(1)
    assert mail["To"] == "alice@example.org"
    assert inbox.envelopes[0][1] == ["alice@example.org"]
    link = re.search(r"https://manieval\.example\.org/verify\?token=\S+", body_of(mail))
    assert link, body_of(mail)
    headers = token_for(client, "alice")

    refused = submit(client, headers)
    assert refused.status_code == 403
    assert "verify your email address" in refused.json()["error"]["message"]

    # Opening the link (as a mail scanner would) shows a button and uses nothing up.
    page = client.get(f"/verify?token={token_in(mail)}")
    assert page.status_code == 200
    assert "Confirm my address" in page.text
    r = client.post(f"{API}/auth/verify", json={"token": token_in(mail)})
    assert r.status_code == 200, r.text
    assert client.get(f"{API}/me", headers=headers).json()["user"]["email_verified"] is True
    assert submit(client, headers).status_code == 202

    again = client.post(f"{API}/auth/verify", json={"token": token_in(mail)})
    assert again.status_code == 422
    assert "token" in again.json()["error"]["fields"]


def test_a_new_verification_link_on_request_and_none_once_verified(
    client: TestClient, inbox: Inbox
) -> None:
    register(client, "bea")
    headers = token_for(client, "bea")
    r = client.post(f"{API}/auth/verify/resend", headers=headers)
    assert r.status_code == 202
    first, second = inbox.wait(2)
    assert token_in(first) != token_in(second)
    assert client.post(f"{API}/auth/verify", json={"token": token_in(second)}).status_code == 200
    r = client.post(f"{API}/auth/verify/resend", headers=headers)
    assert r.status_code == 202
    assert "verified already" in r.json()["message"]
    assert len(inbox.messages) == 2


def test_resending_is_rate_limited(
    settings: Settings, sessions: sessionmaker[Session], inbox: Inbox
) -> None:
    app = create_app(
        settings.model_copy(update={"mail_rate": "2/hour"}),
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app, base_url="http://testserver") as client:
        register(client, "cleo")
        headers = token_for(client, "cleo")
        codes = [
            client.post(f"{API}/auth/verify/resend", headers=headers).status_code for _ in "abc"
        ]
    assert codes == [202, 202, 429]
    assert len(inbox.wait(3)) == 3  # the registration's and two more


def test_a_failed_send_is_logged_and_the_answer_is_unchanged(
    settings: Settings,
    sessions: sessionmaker[Session],
    caplog: pytest.LogCaptureFixture,
) -> None:
    broken = settings.model_copy(update={"smtp_port": free_port()})  # nothing listens there
    app = create_app(
        broken,
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(broken),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with TestClient(app, base_url="http://testserver") as client, caplog.at_level(logging.WARNING):
        register(client, "dora")
    assert any("could not send mail to dora@example.org" in r.getMessage() for r in caplog.records)


# Password reset ------------------------------------------------------------------------------


def test_password_reset_link_works_once_and_ends_sessions(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_user(db, "erin")
    r = client.post(f"{API}/session", json={"login": "erin", "password": PASSWORD})
    assert r.status_code == 200
    assert client.get(f"{API}/me").status_code == 200

    r = client.post(f"{API}/auth/password-reset", json={"email": "Erin@Example.org"})
    assert r.status_code == 202
    [mail] = inbox.wait(1)
    assert mail["To"] == "erin@example.org"
    assert "https://manieval.example.org/reset-password?token=" in body_of(mail)
    token = token_in(mail)
    assert client.get(f"/reset-password?token={token}").status_code == 200  # looking is free

    done = client.post(
        f"{API}/auth/password-reset/confirm", json={"token": token, "password": NEW_PASSWORD}
    )
    assert done.status_code == 200, done.text
    assert client.get(f"{API}/me").status_code == 401  # the browser session ended
    old = client.post(f"{API}/session", json={"login": "erin", "password": PASSWORD})
    assert old.status_code == 401
    new = client.post(f"{API}/session", json={"login": "erin", "password": NEW_PASSWORD})
    assert new.status_code == 200

    again = client.post(
        f"{API}/auth/password-reset/confirm",
        json={"token": token, "password": "another fine kettle of fish"},
    )
    assert again.status_code == 422
    assert "token" in again.json()["error"]["fields"]


def test_an_expired_reset_link_is_refused(client: TestClient, inbox: Inbox, db: Session) -> None:
    make_user(db, "fay")
    client.post(f"{API}/auth/password-reset", json={"email": "fay@example.org"})
    token = token_in(inbox.wait(1)[0])
    [row] = tokens_of(db, "fay")
    assert row.expires_at - row.created_at == timedelta(minutes=60)
    db.execute(
        update(EmailToken)
        .where(EmailToken.id == row.id)
        .values(expires_at=datetime.now(UTC) - timedelta(seconds=1))
    )
    db.commit()
    r = client.post(
        f"{API}/auth/password-reset/confirm", json={"token": token, "password": NEW_PASSWORD}
    )
    assert r.status_code == 422
    assert "expired" in r.json()["error"]["message"]
    assert "not valid" in client.get(f"/reset-password?token={token}").text


def test_reset_links_expire_by_the_clock(db: Session) -> None:
    user = make_user(db, "gus")
    letters = Letters(
        sender="ManiEval <m@example.org>",
        base_url="https://x.example",
        verify_for=timedelta(hours=1),
        reset_for=timedelta(minutes=30),
    )
    mail = verification.password_reset_mail(db, email=user.email, letters=letters)
    assert mail is not None
    token = token_in(mail)
    later = datetime.now(UTC) + timedelta(minutes=31)
    assert not verification.reset_link_works(db, token=token, now=later)
    with pytest.raises(Invalid):
        verification.reset_password(db, token=token, password=NEW_PASSWORD, now=later)
    assert verification.reset_link_works(db, token=token)


def test_link_tokens_are_stored_only_hashed(client: TestClient, inbox: Inbox, db: Session) -> None:
    make_user(db, "hana")
    client.post(f"{API}/auth/password-reset", json={"email": "hana@example.org"})
    token = token_in(inbox.wait(1)[0])
    [row] = tokens_of(db, "hana")
    assert row.purpose == "reset"
    assert row.digest == hashlib.sha256(token.encode()).hexdigest()
    stored = [str(getattr(row, c.key)) for c in EmailToken.__table__.columns]
    assert not any(token in value for value in stored)


def test_a_weak_new_password_is_refused_and_the_link_still_works(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_user(db, "ivan")
    client.post(f"{API}/auth/password-reset", json={"email": "ivan@example.org"})
    token = token_in(inbox.wait(1)[0])
    weak = client.post(
        f"{API}/auth/password-reset/confirm", json={"token": token, "password": "password123456"}
    )
    assert weak.status_code == 422
    assert "password" in weak.json()["error"]["fields"]
    ok = client.post(
        f"{API}/auth/password-reset/confirm", json={"token": token, "password": NEW_PASSWORD}
    )
    assert ok.status_code == 200


def test_an_unknown_address_gets_the_identical_answer(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_user(db, "jade")
    known = client.post(f"{API}/auth/password-reset", json={"email": "jade@example.org"})
    unknown = client.post(f"{API}/auth/password-reset", json={"email": "nobody@example.org"})
    assert known.status_code == unknown.status_code == 202
    assert known.json()["message"].replace("jade", "nobody") == unknown.json()["message"]
    assert dict(known.headers).keys() == dict(unknown.headers).keys()
    assert [m["To"] for m in inbox.wait(1)] == ["jade@example.org"]  # and no other mail
    assert len(db.scalars(select(EmailToken)).all()) == 1


@pytest.mark.parametrize("email", ["kim@example.org", "nobody@example.org"])
def test_reset_requests_are_limited_whether_the_address_exists_or_not(
    settings: Settings, sessions: sessionmaker[Session], inbox: Inbox, email: str
) -> None:
    app = create_app(
        settings.model_copy(update={"mail_rate": "2/hour"}),
        sessions=sessions,
        work=RecordingQueue(),
        resolve=fake_resolve_for(settings),
        limiter=MemoryRateLimiter(),
        background=False,
    )
    with sessions() as db:
        make_user(db, "kim")
    with TestClient(app, base_url="http://testserver") as client:
        answers = [client.post(f"{API}/auth/password-reset", json={"email": email}) for _ in "abc"]
    assert [r.status_code for r in answers] == [202, 202, 429]
    assert "Retry-After" in answers[2].headers


# Email change --------------------------------------------------------------------------------


def test_an_email_change_takes_effect_once_the_new_address_is_verified(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_user(db, "lena")
    headers = token_for(client, "lena")
    r = client.patch(
        f"{API}/me",
        json={"email": "lena@new.example.org", "current_password": PASSWORD},
        headers=headers,
    )
    assert r.status_code == 202, r.text
    [mail] = inbox.wait(1)
    assert mail["To"] == "lena@new.example.org"
    me = client.get(f"{API}/me", headers=headers).json()["user"]
    assert (me["email"], me["email_verified"]) == ("lena@example.org", True)

    assert client.post(f"{API}/auth/verify", json={"token": token_in(mail)}).status_code == 200
    me = client.get(f"{API}/me", headers=headers).json()["user"]
    assert (me["email"], me["email_verified"]) == ("lena@new.example.org", True)
    # A reset now goes to the new address only.
    client.post(f"{API}/auth/password-reset", json={"email": "lena@example.org"})
    client.post(f"{API}/auth/password-reset", json={"email": "lena@new.example.org"})
    assert [m["To"] for m in inbox.wait(2)] == ["lena@new.example.org", "lena@new.example.org"]


def test_an_unverified_account_that_changes_address_verifies_the_new_one(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    register(client, "mia")
    headers = token_for(client, "mia")
    first = inbox.wait(1)[0]
    client.patch(
        f"{API}/me",
        json={"email": "mia@typo-fixed.example", "current_password": PASSWORD},
        headers=headers,
    )
    change = inbox.wait(2)[1]
    assert client.post(f"{API}/auth/verify", json={"token": token_in(change)}).status_code == 200
    # The link sent to the old address can no longer move the account back.
    assert client.post(f"{API}/auth/verify", json={"token": token_in(first)}).status_code == 422
    me = client.get(f"{API}/me", headers=headers).json()["user"]
    assert (me["email"], me["email_verified"]) == ("mia@typo-fixed.example", True)


def test_an_email_change_to_a_taken_address_answers_the_same(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_user(db, "nico")
    make_user(db, "owen")
    headers = token_for(client, "nico")
    taken = client.patch(
        f"{API}/me",
        json={"email": "owen@example.org", "current_password": PASSWORD},
        headers=headers,
    )
    free = client.patch(
        f"{API}/me",
        json={"email": "nico2@example.org", "current_password": PASSWORD},
        headers=headers,
    )
    assert taken.status_code == free.status_code == 202
    assert taken.json()["message"].replace("owen@", "nico2@") == free.json()["message"]
    to_owen, to_nico2 = inbox.wait(2)
    assert to_owen["To"] == "owen@example.org"
    assert "already belongs to an account" in body_of(to_owen)
    assert TOKEN.search(body_of(to_owen)) is None
    assert to_nico2["To"] == "nico2@example.org"


def test_an_email_change_needs_the_current_password(
    client: TestClient, inbox: Inbox, db: Session
) -> None:
    make_user(db, "pia")
    headers = token_for(client, "pia")
    r = client.patch(
        f"{API}/me",
        json={"email": "pia@elsewhere.example", "current_password": "not my password at all"},
        headers=headers,
    )
    assert r.status_code == 422
    assert "current_password" in r.json()["error"]["fields"]
    assert inbox.messages == []


# Transports ----------------------------------------------------------------------------------


def test_the_folder_mailer_writes_a_readable_eml(tmp_path: Path) -> None:
    letters = Letters(
        sender="ManiEval <manieval@example.org>",
        base_url="http://127.0.0.1:8000",
        verify_for=timedelta(hours=48),
        reset_for=timedelta(minutes=60),
    )
    message = letters.verification(
        username="quinn", email="q@example.org", token="t" * 43, change=False
    )
    FolderMailer(tmp_path / "mail").send(message)
    [path] = (tmp_path / "mail").glob("*.eml")
    assert path.stat().st_mode & 0o777 == 0o600
    raw = path.read_bytes()
    assert b"http://127.0.0.1:8000/verify?token=" + b"t" * 43 in raw  # the link as it is
    parsed = message_from_bytes(raw, policy=policy.default)
    assert parsed["To"] == "q@example.org"
    assert parsed["Subject"] == "Confirm your email address for ManiEval"
    assert "48 hours" in body_of(parsed)  # type: ignore[arg-type]


def test_the_embedded_default_writes_mail_to_the_data_dir_and_says_so_at_start(
    tmp_path: Path, sessions: sessionmaker[Session], caplog: pytest.LogCaptureFixture
) -> None:
    settings = Settings(dev_mode=True, data_dir=tmp_path, cookie_secure=False)
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with caplog.at_level(logging.INFO), TestClient(app, base_url="http://testserver") as client:
        body = {"username": "rosa", "email": "rosa@example.org", "password": PASSWORD}
        assert client.post(f"{API}/users", json=body).status_code == 201
    assert any(str(tmp_path / "mail") in r.getMessage() for r in caplog.records)
    [path] = (tmp_path / "mail").glob("*.eml")
    mail = message_from_bytes(path.read_bytes(), policy=policy.default)
    assert mail["To"] == "rosa@example.org"
    assert "http://testserver/verify?token=" in body_of(mail)  # type: ignore[arg-type]


def _certificate(folder: Path) -> tuple[Path, Path]:
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.now(UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(minutes=5))
        .not_valid_after(now + timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = folder / "smtp.crt", folder / "smtp.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return cert_path, key_path


@pytest.mark.parametrize("security", ["starttls", "ssl"])
def test_smtp_over_tls_with_credentials(tmp_path: Path, security: str) -> None:
    cert, key = _certificate(tmp_path)
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(cert, key)
    inbox = Inbox()

    def authenticate(server: Any, session: Any, envelope: Any, mechanism: str, data: Any) -> Any:
        ok = isinstance(data, LoginPassword) and (data.login, data.password) == (
            b"mailer",
            b"s3cret-smtp-password",
        )
        if ok:
            inbox.logins.append(data.login.decode())
        return AuthResult(success=ok)

    port = free_port()
    tls: dict[str, Any] = (
        {"tls_context": context, "require_starttls": True}
        if security == "starttls"
        else {"ssl_context": context}
    )
    controller = Controller(
        inbox,
        hostname="127.0.0.1",
        port=port,
        authenticator=authenticate,
        # aiosmtpd counts only STARTTLS as TLS; on implicit TLS the whole connection is.
        auth_require_tls=security == "starttls",
        **tls,
    )
    controller.start()
    try:
        mailer = SmtpMailer(
            host="127.0.0.1",
            port=port,
            security=security,  # type: ignore[arg-type]
            username="mailer",
            password=SecretStr("s3cret-smtp-password"),
            ca_file=cert,
            timeout=WAIT_S,
        )
        message = EmailMessage()
        message["From"] = "ManiEval <m@example.org>"
        message["To"] = "sam@example.org"
        message["Subject"] = "hello"
        message.set_content("over TLS")
        mailer.send(message)
        [received] = inbox.wait(1)
    finally:
        controller.stop()
    assert received["Subject"] == "hello"
    assert inbox.logins == ["mailer"]


def test_starttls_is_never_skipped_when_the_server_lacks_it(smtp_server: tuple[Inbox, int]) -> None:
    inbox, port = smtp_server
    inbox.clear()
    message = EmailMessage()
    message["To"] = "tom@example.org"
    message.set_content("x")
    with pytest.raises(OSError, match="STARTTLS"):
        SmtpMailer(host="127.0.0.1", port=port, security="starttls", timeout=WAIT_S).send(message)
    assert inbox.messages == []


@pytest.mark.parametrize(
    ("changes", "problem"),
    [
        ({"mail_backend": "smtp"}, "MANIEVAL_SMTP_HOST"),
        ({"mail_backend": "smtp", "smtp_host": "mail.example.org"}, "MANIEVAL_PUBLIC_URL"),
        ({"public_url": "javascript:alert(1)"}, "MANIEVAL_PUBLIC_URL"),
        ({"smtp_username": "x"}, "MANIEVAL_SMTP_PASSWORD"),
        (
            {
                "smtp_host": "mail.example.org",
                "smtp_security": "none",
                "smtp_username": "x",
                "smtp_password": "y",
            },
            "unencrypted",
        ),
        ({"mail_from": "not an address"}, "MANIEVAL_MAIL_FROM"),
        ({"mail_rate": "often"}, "rate"),
    ],
)
def test_mail_settings_fail_fast(changes: dict[str, str], problem: str) -> None:
    secrets = dict.fromkeys(("secret_key", "seed_secret", "worker_token"), "k" * 32)
    with pytest.raises(ValidationError, match=problem):
        Settings(**secrets, **changes)  # type: ignore[arg-type]


def test_verification_is_required_where_mail_reaches_people_unless_turned_off() -> None:
    secrets = dict.fromkeys(("secret_key", "seed_secret", "worker_token"), "k" * 32)
    smtp = {"mail_backend": "smtp", "smtp_host": "mail.example.org"}
    public = {"public_url": "https://manieval.example.org"}
    assert Settings(**secrets, **smtp, **public).email_verification_required  # type: ignore[arg-type]
    # Mails only in the data directory's folder: nobody could verify, so nobody must.
    assert not Settings(**secrets).email_verification_required  # type: ignore[arg-type]
    assert not Settings(dev_mode=True).email_verification_required
    off = Settings(**secrets, require_verified_email=False)  # type: ignore[arg-type]
    assert not off.email_verification_required
