"""The downloads are built in memory from the running sources: reproducible, and each wheel's
RECORD hashes every file it holds (pip checks it on install)."""

from __future__ import annotations

import base64
import hashlib
import io
import zipfile

from server.downloads.artifacts import cli_spec, sdk_spec, template_archive
from server.downloads.wheel import build_wheel


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
