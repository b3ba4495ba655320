"""`python3 -m manieval_sdk.openpi --mapping mapping.toml [--command CMD] [--url ws://...]`:
the policy image's command when its policy is an openpi server (docs/policy-servers.md)."""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

from manieval_sdk.openpi.bridge import OpenpiBridge
from manieval_sdk.openpi.connection import ServerError, ServerProcess, client_modules
from manieval_sdk.openpi.mapping import MappingError, load_mapping, loopback_url
from manieval_sdk.serve import serve


def main(argv: Sequence[str] | None = None) -> None:
    """Start (or find) the server, then answer the evaluator through it until it closes."""
    parser = argparse.ArgumentParser(
        prog="python3 -m manieval_sdk.openpi",
        description="Serve an openpi policy server to the ManiEval evaluator.",
    )
    parser.add_argument("--mapping", required=True, type=Path, help="the mapping file (TOML)")
    parser.add_argument(
        "--command",
        help="start the policy server with this command line (default: the mapping's "
        "[server] command; with neither, connect to a server already running)",
    )
    parser.add_argument(
        "--url",
        help="the server's ws:// address on the loopback interface (default: the "
        "mapping's [server] url, else ws://127.0.0.1:8000)",
    )
    args = parser.parse_args(argv)
    try:
        mapping = load_mapping(args.mapping)
        url = loopback_url(args.url or mapping.server.url)
        client_modules()  # fail now, not at the first task, when openpi-client is missing
        command = shlex.split(args.command) if args.command is not None else mapping.server.command
        server = ServerProcess(command) if command else None
    except (MappingError, ServerError) as exc:
        sys.exit(f"manieval_sdk.openpi: {exc}")
    bridge = OpenpiBridge(mapping, url=url, server=server)
    try:
        serve(bridge)
    finally:
        bridge.close()


if __name__ == "__main__":
    main()
