"""Serve an openpi policy server to ManiEval: `python3 -m manieval_sdk.openpi --mapping FILE`.

The bridge (`OpenpiBridge`) starts the participant's openpi-protocol server inside the policy
image (or connects to one already running there), on the loopback interface only, and maps
ManiSkill observations to the server's keys as a mapping file says (docs/policy-servers.md).
It needs openpi-client and websockets (`pip install 'manieval-sdk[openpi]'`), imported only
when it connects; the mapping and its transforms need numpy alone.
"""

from manieval_sdk.openpi.bridge import OpenpiBridge
from manieval_sdk.openpi.mapping import Mapping, MappingError, load_mapping

__all__ = ["Mapping", "MappingError", "OpenpiBridge", "load_mapping"]
