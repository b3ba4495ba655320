"""The openpi bridge as a ManiEval policy (manieval_sdk.openpi.bridge and its command line),
with the example's server policy answering in this process instead of over a WebSocket; and
what it says when openpi-client is missing, which it is in the service's virtualenv.

The bridge over a real WebSocket, in the policy image: tests/worker/test_openpi_image.py.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from manieval_sdk import TaskSpec
from manieval_sdk.openpi import OpenpiBridge, load_mapping
from manieval_sdk.openpi.connection import INSTALL_HINT, ServerError, client_modules
from tests.evaluator.openpi_reference import InProcess, example_server
from tests.evaluator.test_openpi_mapping import EXAMPLE, rgbd_obs, space


def in_process(*, fail_on_call: int | None = None) -> InProcess:
    return InProcess(example_server(EXAMPLE), fail_on_call=fail_on_call)


def pick_cube_spec(instruction: str = "") -> TaskSpec:
    return TaskSpec(
        env_id="PickCube-v1",
        obs_mode="rgbd",
        control_mode="pd_ee_delta_pose",
        control_freq=20,
        max_episode_steps=50,
        action_low=-np.ones(7, np.float32),
        action_high=np.ones(7, np.float32),
        observation_space=space(rgbd_obs()),
        instruction=instruction,
    )


def bridge_to(connections: list[InProcess]) -> OpenpiBridge:
    """A bridge that gets these connections, one per (re)connect, in order."""
    opened = iter(connections)
    return OpenpiBridge(load_mapping(EXAMPLE / "mapping.toml"), connect=lambda: next(opened))


def test_the_bridge_sends_the_mapped_request_and_answers_the_servers_actions() -> None:
    server = in_process()
    bridge = bridge_to([server])
    bridge.setup(pick_cube_spec(instruction="pick up the red cube"))
    obs = rgbd_obs()
    obs["sensor_data"]["base_camera"]["rgb"][:] = 0
    obs["sensor_data"]["base_camera"]["rgb"][:16, :16, 0] = 255  # red, top left
    chunk = np.asarray(bridge.act(obs))
    (request,) = server.requests
    assert request["observation/image"].shape == (96, 96, 3)  # the server's metadata size
    assert request["prompt"] == "pick up the red cube"
    assert chunk.shape == (8, 7)  # the server's chunk, its 8 values cut to the task's 7
    assert chunk[0, 0] > 0  # towards the top left
    assert chunk[0, 1] > 0
    assert chunk[0, 6] == 1.0  # gripper open


def test_without_an_instruction_the_mappings_default_prompt_goes() -> None:
    server = in_process()
    bridge = bridge_to([server])
    bridge.setup(pick_cube_spec())
    bridge.act(rgbd_obs())
    assert server.requests[0]["prompt"] == "pick up the cube"


def test_a_failed_request_fails_its_call_and_the_next_one_connects_again() -> None:
    failing, fresh = in_process(fail_on_call=2), in_process()
    bridge = bridge_to([failing, fresh])
    bridge.setup(pick_cube_spec())
    bridge.act(rgbd_obs())
    with pytest.raises(ServerError, match="RuntimeError: inference 2 fails"):
        bridge.act(rgbd_obs())
    bridge.act(rgbd_obs())
    assert (len(failing.requests), len(fresh.requests)) == (2, 1)


def test_a_server_that_cannot_be_reached_ends_the_policy() -> None:
    def unreachable() -> InProcess:  # as OpenpiConnection.open says it
        raise ServerError("nothing answered on ws://127.0.0.1:8000 within 100 s")

    bridge = OpenpiBridge(load_mapping(EXAMPLE / "mapping.toml"), connect=unreachable)
    with pytest.raises(SystemExit, match=r"manieval_sdk\.openpi: nothing answered on ws://"):
        bridge.setup(pick_cube_spec())


def test_a_mapping_that_does_not_fit_the_task_fails_its_setup() -> None:
    bridge = bridge_to([in_process()])
    spec = pick_cube_spec()
    state_only = TaskSpec(**{**spec.__dict__, "obs_mode": "state_dict"})
    state_only.observation_space.pop("sensor_data")
    with pytest.raises(ValueError, match="the observation has no 'sensor_data'"):
        bridge.setup(state_only)


def test_without_openpi_client_the_bridge_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "openpi_client", None)  # as if not installed
    with pytest.raises(ServerError, match=r"pip install 'manieval-sdk\[openpi\]'"):
        client_modules()


def run_bridge(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "manieval_sdk.openpi", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--mapping", "nowhere.toml"], "nowhere.toml: cannot read the mapping file"),
        (
            ["--mapping", str(EXAMPLE / "mapping.toml"), "--url", "ws://10.1.2.3:8000"],
            "not on the loopback interface",
        ),
    ],
)
def test_the_command_refuses_a_bad_mapping_or_url_before_starting_anything(
    tmp_path: Path, args: list[str], message: str
) -> None:
    done = run_bridge(tmp_path, *args)
    assert done.returncode == 1
    assert message in done.stderr
    assert "started the policy server" not in done.stderr


def test_the_command_says_what_to_install_before_starting_the_server(tmp_path: Path) -> None:
    try:
        client_modules()
    except ServerError:
        pass
    else:
        pytest.skip("openpi-client is installed here")
    done = run_bridge(tmp_path, "--mapping", str(EXAMPLE / "mapping.toml"))
    assert done.returncode == 1
    assert INSTALL_HINT in done.stderr
    assert "started the policy server" not in done.stderr
