"""Settings: safe production defaults, clear errors, the embedded dev defaults."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.kit.settings import Settings

STRONG = "x" * 32


def test_production_requires_every_secret(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("MANIEVAL_DEV_MODE", raising=False)
    with pytest.raises(ValidationError, match="MANIEVAL_SECRET_KEY must be set"):
        Settings()
    with pytest.raises(ValidationError, match="at least 32 characters"):
        Settings(secret_key="short", seed_secret=STRONG, worker_token=STRONG)
    ok = Settings(secret_key=STRONG, seed_secret=STRONG, worker_token=STRONG)
    assert ok.cookie_secure
    assert not ok.allow_local_policies


def test_dev_mode_generates_secrets_once_and_keeps_them_private(tmp_path: Path) -> None:
    first = Settings(dev_mode=True, data_dir=tmp_path)
    key = first.secret("secret_key")
    assert len(key) >= 32
    assert Settings(dev_mode=True, data_dir=tmp_path).secret("secret_key") == key
    assert first.secret("seed_secret") != key
    mode = (tmp_path / "secrets.json").stat().st_mode
    assert stat.S_IMODE(mode) == 0o600
    assert first.resolved_database_url == f"sqlite:///{tmp_path / 'manieval.db'}"


def test_environment_lists_and_rates(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("MANIEVAL_DEV_MODE", "true")
    monkeypatch.setenv("MANIEVAL_ALLOWED_REGISTRIES", "ghcr.io, registry.example.org:5000")
    monkeypatch.setenv("MANIEVAL_DATA_DIR", str(tmp_path))
    s = Settings()
    assert s.allowed_registries == ["ghcr.io", "registry.example.org:5000"]
    assert s.rate("login").limit == 10
    monkeypatch.setenv("MANIEVAL_LOGIN_RATE", "lots")
    with pytest.raises(ValidationError):
        Settings()
