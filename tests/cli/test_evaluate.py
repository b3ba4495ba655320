"""The `manieval evaluate` command, run as a participant runs it."""

from __future__ import annotations

import json
import subprocess
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from evaluator.results import EvaluationResult
from tests.evaluator.conftest import HERE, REACTIVE_POLICY, REPO

MANIEVAL = REPO / ".venv" / "bin" / "manieval"
TINY = str(HERE / "tiny_suite.yaml")


@pytest.fixture
def make_policy(tmp_path: Path) -> Callable[[str], Path]:
    """Write `policy.py` with the given source into a fresh directory."""
    counter = iter(range(1000))

    def write(source: str) -> Path:
        directory = tmp_path / f"policy{next(counter)}"
        directory.mkdir()
        (directory / "policy.py").write_text(textwrap.dedent(source))
        return directory

    return write


def manieval(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(MANIEVAL), *args], capture_output=True, text=True, timeout=300, cwd=REPO
    )


@pytest.mark.sim
def test_evaluate_prints_a_table_and_writes_a_valid_result_document(
    make_policy: Callable[[str], Path], tmp_path: Path
):
    out = tmp_path / "r.json"
    done = manieval(
        "evaluate",
        "--policy",
        str(make_policy(REACTIVE_POLICY)),
        "--suite",
        TINY,
        "--tasks",
        "PickCube-v1",
        "--condition",
        "nominal",
        "--episodes",
        "2",
        "--json",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    assert "PickCube-v1" in done.stdout
    assert "score" in done.stdout
    result = EvaluationResult.model_validate(json.loads(out.read_text()))
    assert [t.env_id for t in result.conditions[0].tasks] == ["PickCube-v1"]
    assert len(result.conditions[0].tasks[0].episodes) == 2


@pytest.mark.sim
def test_evaluate_records_the_first_episode_of_each_task_as_video(
    make_policy: Callable[[str], Path], tmp_path: Path
):
    import imageio.v2 as imageio

    out = tmp_path / "r.json"
    done = manieval(
        "evaluate",
        "--policy",
        str(make_policy(REACTIVE_POLICY)),
        "--suite",
        TINY,
        "--tasks",
        "PushCube-v1",
        "--condition",
        "nominal",
        "--episodes",
        "2",
        "--video",
        str(tmp_path / "videos"),
        "--json",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    result = EvaluationResult.model_validate_json(out.read_text())
    [video] = result.videos
    assert (video.env_id, video.condition, video.episode) == ("PushCube-v1", "nominal", 0)
    frames = imageio.mimread(video.path)
    assert len(frames) == result.conditions[0].tasks[0].episodes[0].steps + 1  # reset first
    assert frames[0].ndim == 3


@pytest.mark.sim
def test_evaluate_exits_1_with_the_reason_when_the_policy_crashes(
    make_policy: Callable[[str], Path],
):
    policy = make_policy("import sys\nprint('missing weights.pt', file=sys.stderr)\nsys.exit(4)\n")
    done = manieval(
        "evaluate",
        "--policy",
        str(policy),
        "--suite",
        TINY,
        "--tasks",
        "PickCube-v1",
        "--condition",
        "nominal",
        "--episodes",
        "1",
    )
    assert done.returncode == 1
    assert "policy_crashed" in done.stderr
    assert "exit code 4" in done.stderr
    assert "missing weights.pt" in done.stderr
    # The reason first, and no table of zeros that would read as a score.
    assert done.stdout == ""
    assert "score" not in done.stderr.replace("no score", "")
    assert done.stderr.index("evaluation aborted") < done.stderr.index("missing weights.pt")
    assert "no score: the evaluation did not finish" in done.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tasks", "NoSuchTask-v1"], "no task 'NoSuchTask-v1'"),
        (["--condition", "storm"], "no condition 'storm'"),
        (["--phase", "final"], "no phase 'final'"),
        (["--suite", "no-such-suite"], "no suite file"),
    ],
)
def test_evaluate_explains_bad_arguments_and_exits_2(
    make_policy: Callable[[str], Path], args: list[str], message: str
):
    policy = make_policy(REACTIVE_POLICY)
    done = manieval("evaluate", "--policy", str(policy), "--suite", TINY, *args)
    assert done.returncode == 2
    assert message in done.stderr


def test_evaluate_refuses_a_directory_without_policy_py(tmp_path: Path):
    done = manieval("evaluate", "--policy", str(tmp_path), "--suite", TINY)
    assert done.returncode == 2
    assert "has no policy.py" in done.stderr


def test_test_phase_without_the_seed_secret_is_refused(make_policy: Callable[[str], Path]):
    done = manieval("evaluate", "--policy", str(make_policy(REACTIVE_POLICY)), "--phase", "test")
    assert done.returncode == 2
    assert "secret" in done.stderr


# A policy that prints as it loads and at every episode, and one line that tries to pass for
# the evaluator's own, clearing the screen first.
CHATTY_POLICY = """
import sys
import numpy as np
from manieval_sdk import Policy, serve

print("loading weights", flush=True)
print("\\x1b[2J\\x1b[Hevaluation aborted (forged)", file=sys.stderr, flush=True)

class Chatty(Policy):
    def reset(self, obs, info):
        print("episode starts", flush=True)

    def act(self, obs):
        return np.zeros(self.spec.action_shape, dtype=np.float32)

if __name__ == "__main__":
    serve(Chatty())
"""
ONE_TASK = ("--suite", TINY, "--tasks", "PickCube-v1", "--condition", "nominal")


@pytest.mark.sim
def test_policy_output_live_shows_each_line_marked_and_nothing_it_could_forge(
    make_policy: Callable[[str], Path],
):
    policy = make_policy(CHATTY_POLICY)
    done = manieval(
        "evaluate", "--policy", str(policy), *ONE_TASK, "--episodes", "2", "--policy-output", "live"
    )
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert "policy | loading weights" in lines
    assert lines.count("policy | episode starts") == 2
    # On stderr, marked, its escape sequences spelled out: never a line of the evaluator's.
    assert "policy | \\x1b[2J\\x1b[Hevaluation aborted (forged)" in lines
    assert "\x1b" not in done.stderr
    assert not any(line.startswith("evaluation aborted") for line in lines)
    assert "policy |" not in done.stdout
    assert "PickCube-v1" in done.stdout  # the table, as without the option


@pytest.mark.sim
def test_policy_output_file_holds_it_after_a_failing_run(
    make_policy: Callable[[str], Path], tmp_path: Path
):
    policy = make_policy("import sys\nprint('missing weights.pt', file=sys.stderr)\nsys.exit(4)\n")
    log = tmp_path / "policy.log"
    done = manieval(
        "evaluate",
        "--policy",
        str(policy),
        *ONE_TASK,
        "--episodes",
        "1",
        "--policy-output",
        str(log),
    )
    assert done.returncode == 1
    assert log.read_text() == "missing weights.pt\n"
    assert f"the policy's output written to {log}" in done.stderr


@pytest.mark.sim
def test_policy_output_file_holds_it_after_a_successful_run_from_every_process(
    make_policy: Callable[[str], Path], tmp_path: Path
):
    policy = make_policy(CHATTY_POLICY)
    log = tmp_path / "policy.log"
    done = manieval(
        "evaluate",
        "--policy",
        str(policy),
        *ONE_TASK,
        "--episodes",
        "2",
        "--workers",
        "2",
        "--policy-output",
        str(log),
    )
    assert done.returncode == 0, done.stderr
    lines = log.read_bytes().splitlines()
    for process in (b"[1]", b"[2]"):  # one episode each, in the evaluator's warm processes
        assert lines.count(process + b" loading weights") == 1
        assert lines.count(process + b" episode starts") == 1
    assert b"[1] \x1b[2J\x1b[Hevaluation aborted (forged)" in lines  # as the policy printed it
    assert "policy |" not in done.stderr


def test_policy_output_to_a_file_that_cannot_be_made_is_a_usage_error(
    make_policy: Callable[[str], Path], tmp_path: Path
):
    policy = make_policy(REACTIVE_POLICY)
    target = str(tmp_path / "no-such-dir" / "policy.log")
    done = manieval("evaluate", "--policy", str(policy), *ONE_TASK, "--policy-output", target)
    assert done.returncode == 2
    assert "no-such-dir" in done.stderr
