"""The bundled example policies, which a demo server accepts as ``local:NAME``.

Only these, which an administrator installed with ManiEval, ever run as local processes on a
server: participants' own code comes as container images.
"""

from __future__ import annotations

from pathlib import Path

LOCAL_PREFIX = "local:"
EXAMPLES_DIR = Path(__file__).resolve().parent.parent / "examples" / "policies"


def bundled_policies() -> dict[str, Path]:
    """The bundled example policies by name (directories holding a ``policy.py``)."""
    if not EXAMPLES_DIR.is_dir():
        return {}
    return {p.name: p for p in sorted(EXAMPLES_DIR.iterdir()) if (p / "policy.py").is_file()}
