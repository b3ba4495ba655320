"""The example openpi server's policy answering the bridge in this process: the same requests,
the same actions, without the WebSocket, openpi-client or the container.

Imported by the bridge's tests; and run as a `policy.py` (copied beside the example's
serve_policy.py and mapping.toml) it is the in-process reference the served image must match.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Any

from manieval_sdk.openpi.connection import ServerError


def example_server(directory: Path) -> ModuleType:
    """The example's serve_policy.py from `directory`: its policy needs numpy alone."""
    spec = importlib.util.spec_from_file_location("serve_policy", directory / "serve_policy.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class InProcess:
    """A connection to the example's policy, which fails as its server would: once failed, the
    connection is closed (openpi's server closes it with 1011 after the traceback)."""

    def __init__(self, server: ModuleType, *, fail_on_call: int | None = None) -> None:
        self.metadata = server.METADATA
        self.policy = server.RedSeeker(fail_on_call=fail_on_call)
        self.broken = False
        self.requests: list[dict[str, Any]] = []

    def infer(self, request: dict[str, Any]) -> Any:
        self.requests.append(request)
        try:
            return self.policy.infer(request)
        except Exception as exc:
            self.broken = True
            raise ServerError(f"the policy server failed: {type(exc).__name__}: {exc}") from None

    def close(self) -> None:
        self.broken = True


if __name__ == "__main__":
    from manieval_sdk import serve
    from manieval_sdk.openpi import OpenpiBridge, load_mapping

    here = Path(__file__).resolve().parent
    module = example_server(here)
    serve(OpenpiBridge(load_mapping(here / "mapping.toml"), connect=lambda: InProcess(module)))
