"""The saved login: where it lives, its modes, and that a failed write keeps the old one."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from manieval import credentials
from manieval.credentials import Credentials, CredentialsError


def login(token: str = "mev_a") -> Credentials:
    return Credentials(
        server="http://127.0.0.1:8000", username="alice", token=token, token_id=1, token_name="t"
    )


@pytest.fixture
def config_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    directory = tmp_path / "nested" / "manieval"
    monkeypatch.setenv("MANIEVAL_CONFIG_DIR", str(directory))
    return directory


def test_the_default_location_is_the_users_config_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("MANIEVAL_CONFIG_DIR", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert credentials.credentials_path() == tmp_path / "manieval" / "credentials.json"


def test_saved_login_is_0600_in_a_0700_directory_and_reads_back(config_dir: Path) -> None:
    path = credentials.save(login())
    assert path == config_dir / "credentials.json"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(config_dir.stat().st_mode) == 0o700
    assert credentials.load() == login()


def test_a_failed_write_keeps_the_previous_login_and_leaves_no_temporary_file(
    config_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    credentials.save(login("mev_old"))

    def broken(*_args: object, **_kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(json, "dump", broken)
    with pytest.raises(OSError, match="disk full"):
        credentials.save(login("mev_new"))
    assert credentials.load() == login("mev_old")
    assert [p.name for p in config_dir.iterdir()] == ["credentials.json"]


def test_no_file_is_no_login_and_a_broken_file_is_an_error(config_dir: Path) -> None:
    assert credentials.load() is None
    assert credentials.delete() is False
    config_dir.mkdir(parents=True)
    (config_dir / "credentials.json").write_text("{not json")
    with pytest.raises(CredentialsError, match="cannot be read"):
        credentials.load()
    assert credentials.delete() is True
