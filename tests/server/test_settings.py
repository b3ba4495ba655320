"""Settings: safe production defaults, clear errors, the embedded dev defaults."""

from __future__ import annotations

import json
import stat
import subprocess
import sys
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


def test_a_generated_secret_is_read_once_per_process(tmp_path: Path) -> None:
    settings = Settings(dev_mode=True, data_dir=tmp_path)
    token = settings.secret("worker_token")
    (tmp_path / "secrets.json").write_text('{"worker_token": "changed-behind-our-back"}')
    assert settings.secret("worker_token") == token  # no file read per heartbeat


def test_processes_sharing_a_data_directory_generate_the_same_secrets(tmp_path: Path) -> None:
    code = (
        "import sys; from server.kit.settings import Settings; "
        "print(Settings(dev_mode=True, data_dir=sys.argv[1]).secret('seed_secret'))"
    )
    started = [
        subprocess.Popen(
            [sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True
        )
        for _ in range(4)
    ]
    answers = {p.communicate(timeout=120)[0].strip() for p in started}
    assert len(answers) == 1
    assert answers == {json.loads((tmp_path / "secrets.json").read_text())["seed_secret"]}
