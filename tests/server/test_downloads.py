"""The downloads are built in memory from the running sources: reproducible, and each wheel's
RECORD hashes every file it holds (pip checks it on install)."""

from __future__ import annotations

import base64
import hashlib
import io
import subprocess
import tarfile
import zipfile
from pathlib import Path

import pytest

from server.downloads.artifacts import (
    NotServed,
    cli_spec,
    sdk_spec,
    source_archive,
    source_dir,
    template_archive,
    tracked_source,
)
from server.downloads.wheel import build_wheel


def git(root: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True, timeout=60)


def a_checkout(root: Path) -> Path:
    """A git checkout with the source's shape: tracked files, and beside them what a running
    service accumulates (keys, a virtualenv, an ignored data directory, local files)."""
    root.mkdir()
    git(root, "init", "-q")
    (root / "Makefile").write_text("install:\n\ttrue\n")
    (root / "server").mkdir()
    (root / "server" / "app.py").write_text("app = 1\n")
    (root / "scripts").mkdir()
    script = root / "scripts" / "install-python.sh"
    script.write_text("#!/bin/sh\n")
    script.chmod(0o755)
    (root / ".gitignore").write_text("server/data/\n")
    (root / "server" / "linked.py").symlink_to("/etc/hostname")
    git(root, "add", "Makefile", "server/app.py", "scripts", ".gitignore", "server/linked.py")
    (root / "server" / "tls.key").write_text("PRIVATE\n")  # untracked
    (root / "server" / "data").mkdir()
    (root / "server" / "data" / "secrets.json").write_text("{}\n")  # ignored
    (root / "tests").mkdir()
    (root / "tests" / "test_x.py").write_text("")
    git(root, "add", "tests")  # tracked, but not part of the source download
    return root


def test_the_same_sources_build_the_same_bytes() -> None:
    assert build_wheel(cli_spec()) == build_wheel(cli_spec())
    assert template_archive() == template_archive()


def test_each_wheels_record_hashes_every_file() -> None:
    for spec in (sdk_spec(), cli_spec()):
        wheel = zipfile.ZipFile(io.BytesIO(build_wheel(spec)))
        record_name = next(n for n in wheel.namelist() if n.endswith(".dist-info/RECORD"))
        rows = [line.split(",") for line in wheel.read(record_name).decode().splitlines()]
        recorded = {path: digest for path, digest, _ in rows if path != record_name}
        assert set(recorded) == set(wheel.namelist()) - {record_name}
        for path, digest in recorded.items():
            data = wheel.read(path)
            sha = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
            assert digest == f"sha256={sha}", path


def test_the_sdk_wheel_is_its_pyprojects() -> None:
    spec = sdk_spec()
    assert spec.name == "manieval-sdk"
    assert list(spec.requires) == ["numpy>=1.21", "msgpack>=1.0"]
    assert "manieval_sdk/__init__.py" in spec.files


def test_the_source_is_what_git_tracks_of_its_parts_and_nothing_beside_it(tmp_path: Path) -> None:
    root = a_checkout(tmp_path / "checkout")
    assert tracked_source(root) == ["Makefile", "scripts/install-python.sh", "server/app.py"]
    archive = tarfile.open(fileobj=io.BytesIO(source_archive(root)))
    members = {m.name: m for m in archive.getmembers()}
    assert set(members) == {
        f"{source_dir()}/{name}"
        for name in ("Makefile", "scripts/install-python.sh", "server/app.py")
    }
    assert members[f"{source_dir()}/scripts/install-python.sh"].mode == 0o755
    assert members[f"{source_dir()}/server/app.py"].mode == 0o644
    assert source_archive(root) == source_archive(root)  # reproducible


def test_no_source_is_served_outside_a_git_checkout(tmp_path: Path) -> None:
    (tmp_path / "Makefile").write_text("install:\n")
    with pytest.raises(NotServed, match="git checkout"):
        tracked_source(tmp_path)
    with pytest.raises(NotServed, match="not installed"):
        tracked_source(tmp_path / "elsewhere")
