"""The server's settings: one object, read from ``MANIEVAL_*`` environment variables.

Defaults are the embedded single-machine mode (SQLite in the data directory, the in-process
queue). Production sets ``MANIEVAL_DEV_MODE=false`` (the default), which makes a secret key
mandatory. Every field is documented in ``docs/server.md``.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import threading
from pathlib import Path
from typing import Annotated, Literal

import platformdirs
from pydantic import BeforeValidator, Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from server.kit.ratelimit import Rate


def default_data_dir() -> Path:
    """The data directory when MANIEVAL_DATA_DIR names none."""
    return Path(platformdirs.user_data_dir("manieval", appauthor=False))


def _split(value: object) -> object:
    if isinstance(value, str):
        return [item.strip() for item in value.split(",") if item.strip()]
    return value


CommaList = Annotated[list[str], NoDecode, BeforeValidator(_split)]


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="MANIEVAL_", extra="ignore", frozen=True)

    dev_mode: bool = False
    """Development/demo mode: allows a missing secret key (an ephemeral one is generated)."""

    data_dir: Path = Field(default_factory=default_data_dir)
    """Where the embedded database, policy logs and videos live."""

    database_url: str = ""
    """SQLAlchemy URL; empty means ``sqlite:///<data_dir>/manieval.db``."""

    secret_key: SecretStr | None = None
    """Signs CSRF tokens; required outside dev mode (at least 32 characters)."""

    seed_secret: SecretStr | None = None
    """Derives the hidden test-phase seeds; required outside dev mode."""

    worker_token: SecretStr | None = None
    """Bearer token workers present to the internal API, ``/internal/v1`` (never given to a
    policy); required outside dev mode."""

    worker_token_next: SecretStr | None = None
    """During a rotation, a second accepted worker token (docs/server.md, Architecture)."""

    allowed_registries: CommaList = Field(default_factory=lambda: ["127.0.0.1:5000"])
    """Registries submissions may name (domain[:port]), comma-separated."""

    insecure_registries: CommaList = Field(default_factory=list)
    """Registries spoken to over plain HTTP (a local test registry), comma-separated."""

    registry_timeout: float = 10.0
    """Seconds all the requests of one image pin may take together (manifests, token, index
    entries), whatever the registry does."""
    max_image_bytes: int = 4 * 1024**3
    """Refuse images whose layers sum to more than this."""

    registry_domain: str | None = None
    """The service's own registry as participants and workers name it (``127.0.0.1:5000``,
    ``registry.example.org``); None: the service has no registry of its own (docs/registry.md).
    It counts as allowed; a loopback one is spoken to over plain HTTP."""

    registry_internal_url: str | None = None
    """Where the server itself reaches its registry to pin images (``http://manieval-registry:
    5000`` in a cluster); None: ``registry_domain`` over https (http on loopback)."""

    registry_service: str = "manieval-registry"
    """The registry's ``auth.token.service``: the audience of the tokens the server signs."""

    registry_issuer: str = "manieval"
    """The registry's ``auth.token.issuer``: the issuer of the tokens the server signs."""

    registry_token_ttl_s: int = Field(default=300, ge=10, le=3600)
    """Seconds a registry token is valid; an API token revoked is refused at the next one."""

    registry_key_dir: Path | None = None
    """Directory with ``tls.key`` and ``tls.crt`` that sign registry tokens (a mounted
    ``kubernetes.io/tls`` Secret); None: ``<data_dir>/registry-key``, made on first use in dev
    mode."""

    registry_pull_user: str = "manieval-puller"
    """User name of the pull-only credential (workers, Kubernetes nodes)."""

    registry_pull_password: SecretStr | None = None
    """Password of the pull-only credential; required outside dev mode when the service has a
    registry (at least 32 characters)."""

    registry_token_rate: str = "60/minute"
    """Token requests per client address and per user name (``/registry/token``)."""

    allow_local_policies: bool = False
    """Accept ``local:NAME`` submissions of the bundled example policies (demo only)."""

    policy_gpus: int = Field(default=0, ge=0, le=8)
    """GPUs the service's workers can give one policy (their ``MANIEVAL_POLICY_GPUS``): a
    challenge whose suite asks for more (``policy: {gpus: N}``) refuses submissions, saying
    why, instead of queueing what no worker could run. 0: none."""

    queue: Literal["inline", "celery"] = "inline"
    """``inline``: the embedded worker's threads in the server process (embedded default, no
    Redis);
    ``celery``: Celery workers on Redis (``manieval`` in k8s/, docs/deploy.md)."""

    broker_url: str = "redis://127.0.0.1:6379/0"
    celery_queue: str = "manieval"

    inline_workers: int = Field(default=1, ge=1, le=64)
    """Evaluations the embedded worker runs at once."""
    heartbeat_timeout_s: float = Field(default=180.0, gt=0)
    """A running attempt whose worker has not reported for this long is lost: the reconciler
    ends it `error` (ours) and queues it once more. Also how long a partitioned worker's
    attempt waits before it runs elsewhere."""

    max_running_per_user: int = Field(default=2, ge=1, le=1000)
    """Evaluations of one participant running at once, across challenges (fairness)."""

    rate_limit_backend: Literal["memory", "redis"] = "memory"
    """``memory``: per process; ``redis``: shared by every API process (production)."""
    redis_url: str = "redis://127.0.0.1:6379/0"

    register_rate: str = "5/hour"
    login_rate: str = "10/minute"
    token_rate: str = "10/hour"
    submit_rate: str = "20/hour"

    leaderboard_max_age: float = Field(default=1.0, ge=0, le=3600)
    """Seconds a rendered leaderboard page is served before checking for a newer version."""

    database_retry_after_s: int = Field(default=5, ge=1, le=3600)
    """The ``Retry-After`` of the 503 a request gets while the database is unreachable: how
    long clients (the CLI, workers) wait before they try again."""

    log_format: Literal["text", "json"] = "text"
    """``json``: one JSON object per line (for a log pipeline); ``text`` for people."""
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    metrics_token: SecretStr | None = None
    """When set, ``/metrics`` asks for ``Authorization: Bearer <token>`` (Prometheus's
    ``authorization`` setting); unset, keep ``/metrics`` off the public ingress."""

    session_days: int = 14
    cookie_secure: bool = True
    """Send the session cookie only over HTTPS; the embedded demo turns it off."""

    # input limits (issue 13)
    max_body_bytes: int = Field(default=64 * 1024, ge=1024, le=64 * 1024**2)
    """Largest request body (JSON or form) accepted; a larger one gets 413 before parsing."""
    max_internal_body_bytes: int = Field(default=16 * 1024**2, ge=64 * 1024, le=1024**3)
    """Largest body of a worker's report to ``/internal/v1`` (a result and a log tail)."""
    # episode videos (issue 14, docs/videos.md)
    video_dir: Path | None = None
    """Where the episode videos workers upload are kept (``<video_dir>/<submission>/<attempt>/``);
    None: ``<data_dir>/videos``. On Kubernetes a volume the evaluation Jobs write to as well."""
    max_video_bytes: int = Field(default=16 * 1024**2, ge=64 * 1024, le=1024**3)
    """Largest episode video a worker may upload (also bounded by `max_internal_body_bytes`)."""
    max_videos_per_attempt: int = Field(default=500, ge=0, le=100_000)
    """How many videos one attempt may store; uploads beyond it are refused (413)."""
    max_trajectory_bytes: int = Field(default=64 * 1024**2, ge=64 * 1024, le=1024**3)
    """Largest trajectory file (one task run's `.h5` or `.json`) a worker may upload (also
    bounded by `max_internal_body_bytes`; docs/trajectories.md)."""
    login_failures_per_address: Annotated[str, BeforeValidator(Rate.checked)] = "30/hour"
    """Failed logins one client address may make, whatever account (docs/server.md)."""
    login_failures_per_account_address: Annotated[str, BeforeValidator(Rate.checked)] = "5/hour"
    """Failed logins one client address may make against one account (docs/server.md)."""
    password_min_score: int = Field(default=3, ge=0, le=4)
    """Weakest password accepted, as zxcvbn's score (0 guessable in seconds, 4 very strong)."""

    # email (issue 13): verification and password reset links (docs/server.md, Accounts)
    mail_backend: Literal["folder", "smtp"] = "folder"
    """``folder``: each mail is written as an ``.eml`` file to ``<data_dir>/mail`` (the embedded
    default: a laptop needs no mail server); ``smtp``: sent through ``smtp_host``."""
    mail_from: str = "ManiEval <manieval@localhost>"
    """The ``From`` of the service's mails."""
    smtp_host: str = ""
    smtp_port: int = Field(default=587, ge=1, le=65535)
    smtp_security: Literal["starttls", "ssl", "none"] = "starttls"
    """``starttls`` (usually port 587), ``ssl`` (TLS from the start, usually 465) or ``none``
    (a relay on the loopback address only, when credentials are set)."""
    smtp_username: str | None = None
    smtp_password: SecretStr | None = None
    smtp_ca_file: Path | None = None
    """CA certificates (PEM) the SMTP server's certificate is checked against; unset: the
    system's."""
    smtp_timeout: float = Field(default=10.0, gt=0, le=120)
    """Seconds the SMTP server may take over each step (mail is sent after the answer: a slow
    server delays no request)."""
    public_url: str | None = None
    """Where people reach the site (``https://manieval.example.org``): mailed links start with
    it. Unset: the address of the request, which only a local install can trust (a Host header
    is the client's to choose); required with ``mail_backend=smtp`` outside dev mode."""
    require_verified_email: bool | None = None
    """Whether a participant must verify their email address before submitting; unset: yes
    when mail reaches people (``mail_backend=smtp``) outside dev mode, else no (mails in a
    folder only the operator reads could verify nobody)."""
    verify_link_hours: int = Field(default=48, ge=1, le=24 * 30)
    reset_link_minutes: int = Field(default=60, ge=5, le=24 * 60)
    mail_rate: Annotated[str, BeforeValidator(Rate.checked)] = "5/hour"
    """Mails (verification, password reset) one client address, one account and one
    recipient may each ask for."""

    @model_validator(mode="after")
    def _check_mail(self) -> Settings:
        from email.utils import parseaddr
        from urllib.parse import urlsplit

        if self.mail_backend == "smtp" and not self.smtp_host:
            raise ValueError("MANIEVAL_SMTP_HOST must be set when MANIEVAL_MAIL_BACKEND=smtp")
        if self.mail_backend == "smtp" and self.public_url is None and not self.dev_mode:
            raise ValueError(
                "MANIEVAL_PUBLIC_URL must be set when MANIEVAL_MAIL_BACKEND=smtp: "
                "the links in mails start with it"
            )
        if self.public_url is not None:
            url = urlsplit(self.public_url)
            if (
                url.scheme not in ("http", "https")
                or not url.hostname
                or url.query
                or url.fragment
                or not self.public_url.isascii()
            ):
                raise ValueError("MANIEVAL_PUBLIC_URL must be like https://manieval.example.org")
        if (self.smtp_username is None) != (self.smtp_password is None):
            raise ValueError(
                "set both MANIEVAL_SMTP_USERNAME and MANIEVAL_SMTP_PASSWORD, or neither"
            )
        loopback = self.smtp_host in ("localhost", "127.0.0.1", "::1")
        if self.smtp_password is not None and self.smtp_security == "none" and not loopback:
            raise ValueError(
                "MANIEVAL_SMTP_SECURITY=none would send the SMTP password unencrypted: "
                "use starttls or ssl"
            )
        _, address = parseaddr(self.mail_from)
        if "@" not in address or any(c in self.mail_from for c in "\r\n"):
            raise ValueError(
                "MANIEVAL_MAIL_FROM must be an address like 'ManiEval <x@example.org>'"
            )
        return self

    @property
    def email_verification_required(self) -> bool:
        """Whether submitting needs a verified address (`require_verified_email`, resolved)."""
        if self.require_verified_email is None:
            return self.mail_backend == "smtp" and not self.dev_mode
        return self.require_verified_email

    @model_validator(mode="after")
    def _check(self) -> Settings:
        for name in ("secret_key", "seed_secret", "worker_token"):
            value: SecretStr | None = getattr(self, name)
            if value is None and self.dev_mode:
                continue  # generated and kept in the data directory
            if value is None or len(value.get_secret_value()) < 32:
                raise ValueError(
                    f"MANIEVAL_{name.upper()} must be set to at least 32 characters "
                    "(or MANIEVAL_DEV_MODE=true for a local try-out, which generates it)"
                )
        nxt = self.worker_token_next
        if nxt is not None and len(nxt.get_secret_value()) < 32:
            raise ValueError("MANIEVAL_WORKER_TOKEN_NEXT must be at least 32 characters")
        for name in (
            "register_rate",
            "login_rate",
            "token_rate",
            "submit_rate",
            "registry_token_rate",
        ):
            Rate.parse(getattr(self, name))
        pull = self.registry_pull_password
        if self.registry_domain is not None and not self.dev_mode:
            if pull is None or len(pull.get_secret_value()) < 32:
                raise ValueError(
                    "MANIEVAL_REGISTRY_PULL_PASSWORD must be set to at least 32 characters "
                    "when MANIEVAL_REGISTRY_DOMAIN is set"
                )
        return self

    @property
    def resolved_video_dir(self) -> Path:
        return self.video_dir or self.data_dir / "videos"

    @property
    def resolved_database_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir / 'manieval.db'}"

    def rate(self, name: Literal["register", "login", "token", "submit", "registry_token"]) -> Rate:
        return Rate.parse(getattr(self, f"{name}_rate"))

    def secret(self, name: SecretName) -> str:
        """The secret's value. In dev mode a missing one is generated once and kept (0600) in
        the data directory, so that a restarted demo keeps its sessions and test seeds."""
        value: SecretStr | None = getattr(self, name)
        if value is not None:
            return value.get_secret_value()
        return _generated_secret(self.data_dir / "secrets.json", name)


SecretName = Literal["secret_key", "seed_secret", "worker_token", "registry_pull_password"]


_generated: dict[tuple[str, str], str] = {}
_generated_lock = threading.Lock()


def _generated_secret(path: Path, name: str) -> str:
    """Read (or make) once per process: the internal API checks the worker token at every
    heartbeat. Processes sharing a data directory agree through a lock on the file."""
    key = (str(path.resolve()), name)
    with _generated_lock:
        if (known := _generated.get(key)) is not None:
            return known
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path.with_suffix(".lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
            stored: dict[str, str] = json.loads(path.read_text()) if path.exists() else {}
            if name not in stored:
                stored[name] = secrets.token_urlsafe(32)
                tmp = path.with_suffix(".tmp")
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                with os.fdopen(fd, "w") as f:
                    json.dump(stored, f)
                os.replace(tmp, path)
        _generated[key] = stored[name]
        return stored[name]
