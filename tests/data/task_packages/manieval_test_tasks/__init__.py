"""A task package for ManiEval's tests (docs/task-packages.md): importing it registers
`KeepCubeInRing-v1`, a task of its own built on ManiSkill's PushCube-v1, and
`PickCubeUnreachable-v1`, a broken one (its goal out of reach) for verification's tests.

Tests put `tests/data/task_packages` on PYTHONPATH (a plain module: its version is a hash of
its files); `pip install tests/data/task_packages` installs it as the distribution
`manieval-test-tasks` instead.
"""

from manieval_test_tasks.keep_cube import KeepCubeInRingEnv
from manieval_test_tasks.unreachable import PickCubeUnreachableEnv

__all__ = ["KeepCubeInRingEnv", "PickCubeUnreachableEnv"]
