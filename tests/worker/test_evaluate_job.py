"""The evaluator's entry point in a Job's pod: its job spec, its output, and a real run."""

from __future__ import annotations

import io
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest
import typer
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from evaluator.evaluation import build_result, evaluate
from evaluator.job import (
    MARK,
    EvaluationJob,
    ExternalPolicy,
    JobOutputError,
    ShardReport,
    evaluate_job,
    evaluation_job,
    read_document,
    result_from_logs,
    run_job,
    write_document,
)
from evaluator.plan import build_plan
from evaluator.results import Abort, EpisodeResult, EvaluationResult, episode_records
from evaluator.runner import ShardOutcome
from evaluator.sources import LocalDirectory
from evaluator.suite import Suite, SuiteError
from testkit.k8s_double import (
    POLICY_IMAGE,
)
from tests.evaluator.conftest import REPO, SCRIPTED, tiny_suite
from tests.worker.k8s_specs import (
    TINY_SUITE,
    tiny_evaluation,
)

pytestmark = pytest.mark.long

STARTED = datetime(2026, 5, 1, tzinfo=UTC)
SECRET_SUITE = """
name: hidden
version: 2
tasks:
  - {env_id: PickCube-v1, max_episode_steps: 12, episodes: 2}
  - {env_id: PushCube-v1, max_episode_steps: 12, episodes: 2}
phases:
  test: {seeds: {kind: secret}}
"""


@pytest.fixture
def volume() -> Iterator[Path]:
    """A stand-in for the pod's shared emptyDir, with a short path (sockets allow ~107 bytes)."""
    path = Path(tempfile.mkdtemp(prefix="mev-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


def document(*, reason: str = "the policy raised: boom") -> EvaluationResult:
    plan = tiny_evaluation().plan()
    episodes = [
        (
            0,
            EpisodeResult(
                index=0,
                seed=100,
                success_once=False,
                success_at_end=False,
                steps=3,
                episode_return=0.5,
                wall_time_s=0.2,
                failure="policy_error",
                failure_reason=reason,
            ),
        )
    ]
    outcomes = [ShardOutcome(episodes=episodes)]
    return build_result(plan, POLICY_IMAGE, outcomes, started=STARTED, finished=lambda: STARTED)


def printed(doc: EvaluationResult | ShardReport) -> str:
    out = io.StringIO()
    write_document(doc, out)
    return out.getvalue()


def test_the_job_spec_rebuilds_the_workers_plan_exactly():
    plan = build_plan(
        tiny_suite(), "dev", tasks=["PickCube-v1"], conditions=["nominal"], episodes=2
    )
    job = evaluation_job(plan, suite_yaml=TINY_SUITE.read_text())
    assert job == tiny_evaluation()
    assert EvaluationJob.model_validate_json(job.canonical_json()).plan() == plan


def test_secret_seeds_travel_as_seeds_and_the_secret_does_not():
    suite = Suite.model_validate(yaml.safe_load(SECRET_SUITE))
    plan = build_plan(suite, "test", secret=b"s3cret-seed-key-of-the-server")
    job = evaluation_job(plan, suite_yaml=SECRET_SUITE)
    assert job.plan() == plan
    assert "s3cret" not in job.canonical_json()
    assert job.seeds["PickCube-v1"] == plan.runs[0].seeds


def test_a_plan_the_job_spec_cannot_express_is_refused():
    plan = build_plan(tiny_suite(), "dev", tasks=["PushCube-v1", "PickCube-v1"], episodes=1)
    with pytest.raises(ValueError, match="suite order"):
        evaluation_job(plan, suite_yaml=TINY_SUITE.read_text())


@pytest.mark.parametrize(
    ("changes", "problem"),
    [
        ({"phase": "test"}, "no phase"),
        ({"seeds": {"StackCube-v1": (1,)}}, "no task"),
        ({"conditions": ("windy",)}, "no condition"),
        ({"seeds": {"PickCube-v1": ()}}, "no seeds"),
        ({"suite_yaml": "name: [unclosed"}, "invalid suite"),
    ],
)
def test_a_bad_job_spec_is_a_suite_error(changes: dict[str, object], problem: str):
    job = tiny_evaluation().model_copy(update=changes)
    with pytest.raises(SuiteError, match=problem):
        job.plan()


def test_the_printed_document_is_found_among_other_output():
    doc = document()
    log = "starting\n" + printed(doc) + "Exception ignored in atexit\n"
    assert read_document(log) == doc
    last = [line for line in printed(doc).split("\n") if line][-1]
    assert last.startswith(f"{MARK} END sha256=")


def test_lines_interleaved_into_the_document_are_ignored():
    lines = printed(document()).split("\n")
    lines.insert(2, "a stderr line that landed in the middle")
    assert read_document("\n".join(lines)) == document()


def test_a_long_document_is_split_into_lines_a_runtime_never_splits():
    doc = document(reason="x" * 50_000)
    text = printed(doc)
    assert max(len(line) for line in text.split("\n")) < 16 * 1024
    assert read_document(text) == doc


@settings(max_examples=60, deadline=None)
@given(reason=st.text(max_size=300))
def test_any_reason_text_survives_the_log_unchanged(reason: str):
    doc = document(reason=reason)
    assert read_document(printed(doc) + printed(doc)[:40]) == doc


def test_a_truncated_or_corrupted_document_is_refused():
    text = printed(document())
    with pytest.raises(JobOutputError):
        read_document(text.rsplit(f"{MARK} END", 1)[0])
    with pytest.raises(JobOutputError):
        read_document(text.replace('"steps":3', '"steps":4'))
    with pytest.raises(JobOutputError):
        read_document("Traceback (most recent call last):\n  ...\nMemoryError\n")


def test_the_last_intact_document_wins():
    older, newer = document(reason="old"), document(reason="new")
    assert read_document(printed(older) + printed(newer)) == newer


def shard_report(index: int, shards: int, episodes: list[tuple[int, EpisodeResult]]) -> str:
    versions = document().versions
    report = ShardReport(
        index=index,
        shards=shards,
        policy=POLICY_IMAGE,
        versions=versions,
        started_at=STARTED,
        finished_at=STARTED,
        episodes=episodes,
    )
    return printed(report)


def test_shard_reports_merge_into_one_result_and_an_abort_marks_the_rest_not_run():
    plan = tiny_evaluation(seeds=(1, 2, 3)).plan()
    ok = EpisodeResult(
        index=0,
        seed=1,
        success_once=True,
        success_at_end=True,
        steps=4,
        episode_return=1.0,
        wall_time_s=0.1,
    )
    crashed = ok.model_copy(
        update={"index": 2, "seed": 3, "success_once": False, "failure": "policy_crashed"}
    )
    logs = [shard_report(0, 2, [(0, ok)]), shard_report(1, 2, [(0, crashed)])]
    result = result_from_logs(plan, logs)
    episodes = result.conditions[0].tasks[0].episodes
    assert [(e.seed, e.failure) for e in episodes] == [
        (1, None),
        (2, "not_run"),
        (3, "policy_crashed"),
    ]
    assert result.policy == POLICY_IMAGE
    aborted = ShardReport.model_validate(
        read_document(logs[1]).model_dump()
        | {"abort": (0, 2, Abort(kind="policy_crashed", reason="x"))}
    )
    assert result_from_logs(plan, [logs[0], printed(aborted)]).status == "aborted"


def test_missing_or_misordered_shards_are_refused():
    plan = tiny_evaluation().plan()
    zero, one = shard_report(0, 2, []), shard_report(1, 2, [])
    with pytest.raises(JobOutputError):
        result_from_logs(plan, [zero, ""])
    with pytest.raises(JobOutputError):
        result_from_logs(plan, [one, zero])
    with pytest.raises(JobOutputError):
        result_from_logs(plan, [zero])


def test_a_pod_whose_shard_has_no_episodes_reports_none_without_waiting(volume: Path):
    plan = tiny_evaluation().plan()  # two episodes, three shards: shard 2 is empty
    report = run_job(plan, ExternalPolicy("p"), index=2, shards=3, socket_dir=volume / "ep")
    assert isinstance(report, ShardReport)
    assert (report.index, report.shards, report.episodes) == (2, 3, [])


def test_a_shard_index_outside_the_shard_count_is_refused(volume: Path):
    with pytest.raises(ValueError, match="shard index"):
        run_job(tiny_evaluation().plan(), ExternalPolicy("p"), index=3, shards=3, socket_dir=volume)


def test_the_command_exits_2_on_a_bad_job_spec():
    app = typer.Typer()
    app.command()(evaluate_job)
    runner = CliRunner()
    done = runner.invoke(app, [], env={"MANIEVAL_JOB_SPEC": '{"phase": "dev"}'})
    assert done.exit_code == 2
    assert "bad job spec" in done.output
    done = runner.invoke(app, [], env={"MANIEVAL_JOB_SPEC": ""})
    assert done.exit_code == 2


def test_the_command_reads_the_job_spec_from_the_secrets_file(tmp_path: Path):
    """On Kubernetes the evaluation comes in a file of the Job's Secret volume, not the env."""
    app = typer.Typer()
    app.command()(evaluate_job)
    runner = CliRunner()
    mounted = tmp_path / "evaluation.json"
    mounted.write_text(tiny_evaluation().canonical_json())
    # Read and planned: only then is the shard index checked against the shard count.
    env = {"MANIEVAL_JOB_SPEC_FILE": str(mounted), "MANIEVAL_SHARDS": "2"}
    done = runner.invoke(app, [], env=env | {"JOB_COMPLETION_INDEX": "2"})
    assert done.exit_code == 2
    assert "shard index 2 is not below the shard count 2" in done.output
    mounted.write_text('{"phase": "dev"}')
    done = runner.invoke(app, [], env=env | {"JOB_COMPLETION_INDEX": "0"})
    assert (done.exit_code, "bad job spec" in done.output) == (2, True)
    done = runner.invoke(app, [], env={"MANIEVAL_JOB_SPEC_FILE": str(tmp_path / "absent")})
    assert (done.exit_code, "bad job spec" in done.output) == (2, True)


def start_policy(endpoint_dir: Path) -> subprocess.Popen[bytes]:
    """The policy container: the scripted example, told only where the socket will be."""
    return subprocess.Popen(
        [sys.executable, str(SCRIPTED / "policy.py")],
        cwd=SCRIPTED,
        env={"MANIEVAL_ENDPOINT": f"unix://{endpoint_dir}/policy.sock"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


@pytest.mark.sim
def test_the_pod_entry_point_prints_what_an_in_process_evaluation_gives(volume: Path):
    evaluation = tiny_evaluation()
    endpoint_dir = volume / "endpoint"
    policy = start_policy(endpoint_dir)  # first, as the sidecar starts: it waits for the socket
    env = {k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")}
    env |= {
        "MANIEVAL_JOB_SPEC": evaluation.canonical_json(),
        "MANIEVAL_POLICY": POLICY_IMAGE,
        "MANIEVAL_SHARDS": "1",
        "MANIEVAL_ENDPOINT_DIR": str(endpoint_dir),
    }
    try:
        done = subprocess.run(
            [sys.executable, "-m", "evaluator.job"],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert policy.wait(timeout=30) == 0  # it was told to close, and did
    finally:
        policy.kill()
    assert done.returncode == 0, done.stderr
    assert done.stdout.rstrip("\n").split("\n")[-1].startswith(f"{MARK} END")
    result = read_document(done.stdout)
    assert isinstance(result, EvaluationResult)
    assert (result.status, result.policy) == ("completed", POLICY_IMAGE)
    local = evaluate(evaluation.plan(), LocalDirectory(SCRIPTED))
    assert result.suite == local.suite
    assert episode_records(result) == episode_records(local)
    assert [e.seed for e in result.conditions[0].tasks[0].episodes] == [100, 101]


@pytest.mark.sim
def test_shards_run_in_separate_pods_merge_into_the_same_episodes(volume: Path):
    evaluation = tiny_evaluation(seeds=(100, 101, 102))
    plan = evaluation.plan()
    logs = []
    for index in range(2):
        endpoint_dir = volume / f"pod{index}"
        policy = start_policy(endpoint_dir)
        try:
            report = run_job(
                plan, ExternalPolicy(POLICY_IMAGE), index=index, shards=2, socket_dir=endpoint_dir
            )
        finally:
            policy.kill()
        assert isinstance(report, ShardReport)
        logs.append(printed(report))
    merged = result_from_logs(plan, logs)
    local = evaluate(plan, LocalDirectory(SCRIPTED))
    assert merged.status == "completed"
    assert episode_records(merged) == episode_records(local)


def test_the_pod_entry_point_stops_at_once_on_sigterm(volume: Path):
    """A deleted pod (a cancel, an eviction) gets SIGTERM: the evaluator stops then, not at the
    kubelet's SIGKILL (as a container's PID 1, Python would ignore SIGTERM by default)."""
    endpoint_dir = volume / "endpoint"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")}
    env |= {
        "MANIEVAL_JOB_SPEC": tiny_evaluation().canonical_json(),
        "MANIEVAL_SHARDS": "1",
        "MANIEVAL_ENDPOINT_DIR": str(endpoint_dir),
    }
    job = subprocess.Popen(
        [sys.executable, "-m", "evaluator.job"], cwd=REPO, env=env, stderr=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 300  # it listens for the policy, which never comes
        while not (endpoint_dir / "policy.sock").exists():
            assert job.poll() is None, job.stderr.read() if job.stderr else ""
            assert time.monotonic() < deadline, "the evaluator never listened"
            time.sleep(0.05)
        job.send_signal(signal.SIGTERM)
        assert job.wait(timeout=60) == 128 + signal.SIGTERM  # its handler's exit, not the default
        assert job.stderr is not None
        assert b"manieval evaluate-job: stopped (SIGTERM)" in job.stderr.read()
    finally:
        job.kill()
        job.wait()
