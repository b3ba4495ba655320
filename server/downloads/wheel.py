"""A pure-Python wheel built in memory from source files: deterministic, no build tool needed."""

from __future__ import annotations

import base64
import hashlib
import io
import re
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

EPOCH = (1980, 1, 1, 0, 0, 0)  # the zip format's earliest time: the same bytes on every build


@dataclass(frozen=True)
class WheelSpec:
    """A pure-Python distribution: its metadata and its files (path in the wheel: content)."""

    name: str
    version: str
    summary: str
    requires: Sequence[str]
    requires_python: str
    files: Mapping[str, bytes]
    scripts: Mapping[str, str] = field(default_factory=dict)  # name: "module:function"

    @property
    def filename(self) -> str:
        return f"{_normalised(self.name)}-{self.version}-py3-none-any.whl"


def build_wheel(spec: WheelSpec) -> bytes:
    """The wheel's bytes (PEP 427), its RECORD hashing every file."""
    info = f"{_normalised(spec.name)}-{spec.version}.dist-info"
    entries = dict(sorted(spec.files.items()))
    entries[f"{info}/METADATA"] = _metadata(spec).encode()
    entries[f"{info}/WHEEL"] = (
        b"Wheel-Version: 1.0\nGenerator: manieval\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    )
    if spec.scripts:
        lines = "".join(f"{name} = {target}\n" for name, target in sorted(spec.scripts.items()))
        entries[f"{info}/entry_points.txt"] = f"[console_scripts]\n{lines}".encode()
    record = [f"{path},sha256={_digest(data)},{len(data)}" for path, data in entries.items()]
    entries[f"{info}/RECORD"] = ("\n".join([*record, f"{info}/RECORD,,"]) + "\n").encode()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for path, data in entries.items():
            member = zipfile.ZipInfo(path, EPOCH)
            member.external_attr = 0o644 << 16
            member.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(member, data)
    return out.getvalue()


def _metadata(spec: WheelSpec) -> str:
    lines = [
        "Metadata-Version: 2.1",
        f"Name: {spec.name}",
        f"Version: {spec.version}",
        f"Summary: {spec.summary}",
        "License: Apache-2.0",
        f"Requires-Python: {spec.requires_python}",
        *(f"Requires-Dist: {requirement}" for requirement in spec.requires),
    ]
    return "\n".join(lines) + "\n"


def _digest(data: bytes) -> str:
    return base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def _normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()
