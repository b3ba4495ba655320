"""The participant SDK goes into every policy image, so it must need numpy and msgpack only."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

ALLOWED_THIRD_PARTY = {"manieval_sdk", "numpy", "msgpack"}
# Cython-compiled extensions (msgpack's, numpy's) register these shared-runtime pseudo-modules
# in sys.modules; they come with the allowed packages and are not dependencies of their own.
CYTHON_RUNTIME = re.compile(r"cython_runtime|_cython_\d+_\d+_\d+[a-z0-9]*")

# Runs in a fresh interpreter: report every top-level module that importing the SDK (all of its
# modules) loaded and that is not part of the standard library.
PROBE = """
import json, sys
before = set(sys.modules)
import manieval_sdk, manieval_sdk.policy, manieval_sdk.seeding, manieval_sdk.serve
import manieval_sdk.wire
# The openpi bridge too: openpi-client and websockets are imported when it connects, not before.
import manieval_sdk.openpi, manieval_sdk.openpi.__main__, manieval_sdk.openpi.connection
loaded = {name.partition(".")[0] for name in set(sys.modules) - before}
print(json.dumps(sorted(loaded - set(sys.stdlib_module_names))))
"""


def test_importing_the_sdk_loads_no_third_party_module_but_numpy_and_msgpack(
    tmp_path: Path,
) -> None:
    # cwd is an empty directory so that nothing from the repository root shadows a module.
    completed = subprocess.run(
        [sys.executable, "-c", PROBE],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    third_party = {
        name for name in json.loads(completed.stdout) if not CYTHON_RUNTIME.fullmatch(name)
    }
    assert "manieval_sdk" in third_party
    assert third_party <= ALLOWED_THIRD_PARTY, sorted(third_party - ALLOWED_THIRD_PARTY)
