"""The worker with `executor=kubernetes`: a submission becomes a Job, is watched, and ends.

The official client talks over HTTP to the API-server double; the tests play the Job
controller and the kubelet. In the end-to-end test the "kubelet" really runs the pod: the
evaluator entry point with the env the Job manifest gives it, and the scripted policy next to it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from evaluator.evaluation import build_result, evaluate
from evaluator.job import evaluation_job, write_document
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import Abort, EvaluationResult
from evaluator.runner import ShardOutcome
from evaluator.sources import LocalDirectory
from server.challenges.service import ChallengeOptions, load_challenge, suite_of
from server.kit.settings import Settings
from server.models import State, Submission, utcnow
from server.submissions.reports import report_state
from server.submissions.service import cancel
from tests.evaluator.conftest import REPO, SCRIPTED, episode_records
from tests.factories import SUITE, RecordingQueue, make_challenge, make_user, queue_submission
from tests.worker.k8s_double import (
    EVALUATOR_IMAGE,
    NAMESPACE,
    ApiServerDouble,
    make_spec,
    running_apiserver,
)
from worker.kubernetes.client import KubernetesExecutor
from worker.kubernetes.manifest import build_job, job_name
from worker.kubernetes.watch import resume_watch, run_as_job
from worker.reconcile import reconcile
from worker.run import job_resumer, run_next, runtime_cleaners
from worker.scheduling import claim_next

STARTED = datetime(2026, 5, 1, tzinfo=UTC)


@pytest.fixture
def apiserver() -> Iterator[ApiServerDouble]:
    with running_apiserver() as double:
        yield double


@pytest.fixture
def k8s_settings(settings: Settings, apiserver: ApiServerDouble) -> Settings:
    return settings.model_copy(
        update={
            "executor": "kubernetes",
            "k8s_api_url": apiserver.host,
            "k8s_namespace": NAMESPACE,
            "evaluator_image": EVALUATOR_IMAGE,
            "k8s_poll_interval": 0.05,
        }
    )


class Run:
    """`run_next` in a thread, as a Celery task would run it."""

    def __init__(self, sessions: sessionmaker[Session], settings: Settings) -> None:
        self.sessions = sessions
        self.outcome: tuple[int, State | None] | None = None
        self.thread = threading.Thread(target=self._run, args=(settings,), daemon=True)
        self.thread.start()

    def _run(self, settings: Settings) -> None:
        self.outcome = run_next(self.sessions, settings)

    def wait(self) -> State | None:
        self.thread.join(timeout=120)
        assert not self.thread.is_alive(), "the worker did not end the attempt"
        assert self.outcome is not None
        return self.outcome[1]

    def submission(self, sid: int) -> Submission:
        with self.sessions() as db:
            submission = db.get(Submission, sid)
            assert submission is not None
            return submission


def until(check: Callable[[], object], what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        time.sleep(0.02)


@pytest.fixture
def queued(committed_sessions: sessionmaker[Session]) -> Submission:
    with committed_sessions() as db:
        challenge = make_challenge(db, quota_concurrent=10, quota_per_day=10)
        submission = queue_submission(db, make_user(db, "alice"), challenge)
        db.commit()
        return submission


def start(
    sessions: sessionmaker[Session], settings: Settings, apiserver: ApiServerDouble, sid: int
) -> Run:
    run = Run(sessions, settings)
    until(lambda: (NAMESPACE, job_name(sid, 1)) in apiserver.jobs, "the Job")
    assert run.submission(sid).state == State.RUNNING
    return run


def plan_of(sessions: sessionmaker[Session], settings: Settings, sid: int) -> EvaluationPlan:
    with sessions() as db:
        submission = db.get(Submission, sid)
        assert submission is not None
        suite = suite_of(submission.challenge)
    return build_plan(suite, "dev", secret=settings.secret("seed_secret").encode())


def printed(document: EvaluationResult) -> str:
    out = tempfile.SpooledTemporaryFile(mode="w+")
    write_document(document, out)  # type: ignore[arg-type]
    out.seek(0)
    return str(out.read())


def run_pod(apiserver: ApiServerDouble, name: str) -> str:
    """Be the kubelet: run the Job's containers as processes; the evaluator's log."""
    manifest = apiserver.jobs[(NAMESPACE, name)]
    (evaluator,) = manifest["spec"]["template"]["spec"]["containers"]
    endpoint = Path(tempfile.mkdtemp(prefix="pod-", dir="/tmp"))
    try:
        env = {k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")}
        env |= {e["name"]: e["value"] for e in evaluator["env"]}
        env |= {"MANIEVAL_ENDPOINT_DIR": str(endpoint), "HOME": str(endpoint)}
        policy = subprocess.Popen(
            [sys.executable, str(SCRIPTED / "policy.py")],
            cwd=SCRIPTED,
            env={"MANIEVAL_ENDPOINT": f"unix://{endpoint}/policy.sock"},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            done = subprocess.run(
                [sys.executable, "-m", "evaluator.job"],
                cwd=REPO,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                timeout=300,
            )
        finally:
            policy.kill()
            policy.wait()
        assert done.returncode == 0, done.stdout
        return done.stdout
    finally:
        shutil.rmtree(endpoint, ignore_errors=True)


@pytest.mark.sim
def test_a_submission_runs_as_a_job_and_scores_as_in_process(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    apiserver.write_log(NAMESPACE, name, "evaluator", "manieval: run 1 episode 0: success\n")
    until(lambda: (run.submission(sid).progress or {}).get("done") == 1, "progress from the log")
    assert (run.submission(sid).progress or {})["condition"] == "obs_noise"  # run 1 of the plan

    log = run_pod(apiserver, name)
    apiserver.succeed(NAMESPACE, name, [log], policy_logs=["policy says hi\n"])
    assert run.wait() == State.SUCCEEDED
    submission = run.submission(sid)
    assert submission.reason.startswith("score ")
    result = EvaluationResult.model_validate(submission.result)
    local = evaluate(plan_of(committed_sessions, k8s_settings, sid), LocalDirectory(SCRIPTED))
    assert episode_records(result) == episode_records(local)
    assert (name, "Foreground") in apiserver.deletions  # collected, then deleted


def test_the_job_is_built_from_the_plan_and_the_settings(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    settings = k8s_settings.model_copy(
        update={"k8s_runtime_class": "gvisor", "policy_cpus": 0.5, "policy_memory_mib": 768}
    )
    run = start(committed_sessions, settings, apiserver, queued.id)
    manifest = apiserver.jobs[(NAMESPACE, job_name(queued.id, 1))]
    pod = manifest["spec"]["template"]["spec"]
    (policy,) = pod["initContainers"]
    assert policy["image"] == queued.pinned_image
    assert policy["resources"]["limits"] | {"ephemeral-storage": "-"} == {
        "cpu": "500m",
        "memory": "768Mi",
        "ephemeral-storage": "-",
    }
    assert pod["runtimeClassName"] == "gvisor"
    env = {e["name"]: e["value"] for e in pod["containers"][0]["env"]}
    plan = plan_of(committed_sessions, settings, queued.id)
    with committed_sessions() as db:
        submission = db.get(Submission, queued.id)
        assert submission is not None
        suite_yaml = submission.challenge.suite_yaml
    assert env["MANIEVAL_JOB_SPEC"] == evaluation_job(plan, suite_yaml=suite_yaml).canonical_json()
    apiserver.fail(NAMESPACE, job_name(queued.id, 1))
    run.wait()


def test_a_policy_abort_fails_the_submission_with_the_pods_reason_and_log(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    apiserver.policy_killed(NAMESPACE, name)
    plan = plan_of(committed_sessions, k8s_settings, sid)
    abort = Abort(kind="policy_crashed", reason="the policy disconnected")
    outcome = ShardOutcome(episodes=[], abort=(0, 0, abort))
    document = build_result(plan, "image", [outcome], started=STARTED)
    apiserver.succeed(NAMESPACE, name, [printed(document)], policy_logs=["Killed\n"])
    assert run.wait() == State.FAILED
    submission = run.submission(sid)
    assert submission.reason.startswith("the policy disconnected; ")
    assert "OOMKilled" in submission.reason
    assert submission.log_tail == "Killed"


@pytest.mark.parametrize(
    ("arrange", "state", "reason"),
    [
        (
            lambda api, name: api.fail(NAMESPACE, name, reason="PodFailurePolicy"),
            State.ERROR,
            "the evaluator failed (PodFailurePolicy",
        ),
        (
            lambda api, name: api.exceed_deadline(NAMESPACE, name),
            State.TIMED_OUT,
            "the evaluation exceeded its time budget",
        ),
        (
            lambda api, name: api.jobs.pop((NAMESPACE, name)),
            State.ERROR,
            "the evaluation's Job eval-",
        ),
        (
            lambda api, name: api.cannot_pull(NAMESPACE, name, "policy"),
            State.ERROR,
            "the evaluation could not start: the policy container: ImagePullBackOff",
        ),
        (
            lambda api, name: api.succeed(NAMESPACE, name, ["no result here\n"]),
            State.ERROR,
            "the evaluation's result could not be read",
        ),
    ],
    ids=["evaluator-failed", "deadline", "job-vanished", "image-pull", "unreadable"],
)
def test_every_way_a_job_ends_gives_a_final_state_with_a_reason(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
    arrange: Callable[[ApiServerDouble, str], object],
    state: State,
    reason: str,
) -> None:
    name = job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, queued.id)
    apiserver.run(NAMESPACE, name, ready=False)
    arrange(apiserver, name)
    assert run.wait() == state
    assert run.submission(queued.id).reason.startswith(reason)


def test_cancel_during_a_run_deletes_the_job_and_its_pods(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    with committed_sessions.begin() as db:
        submission = db.get(Submission, queued.id)
        assert submission is not None
        cancel(db, submission.user, submission)
    assert run.wait() == State.CANCELLED
    assert (name, "Foreground") in apiserver.deletions
    assert apiserver.pods_of(NAMESPACE, name) == []


def test_a_missing_evaluator_image_is_a_configuration_error(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    settings = k8s_settings.model_copy(update={"evaluator_image": None})
    assert Run(committed_sessions, settings).wait() == State.ERROR
    with committed_sessions() as db:
        submission = db.get(Submission, queued.id)
        assert submission is not None
        assert "MANIEVAL_EVALUATOR_IMAGE" in submission.reason
    assert apiserver.jobs == {}


def test_the_reconciler_deletes_jobs_of_attempts_no_longer_active(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, queued.id)
    (clean,) = runtime_cleaners(k8s_settings)
    assert clean({(queued.id, 1)}) == []  # active: kept
    assert clean(set()) == [name]  # e.g. its worker died and the attempt was ended
    assert run.wait() == State.ERROR  # the worker watching it sees it gone, and says so
    assert "disappeared" in run.submission(queued.id).reason


def test_a_suite_that_asks_for_shards_gets_an_indexed_job(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    tmp_path: Path,
) -> None:
    sharded = tmp_path / "sharded.yaml"
    sharded.write_text(SUITE.read_text().replace("name: server-tiny", "name: sharded\nshards: 3"))
    with committed_sessions() as db:
        options = ChallengeOptions(quota_concurrent=10, quota_per_day=10)
        challenge = load_challenge(db, sharded, options, seed_secret="s" * 32)
        sid = queue_submission(db, make_user(db, "bob"), challenge).id
        db.commit()
    run = start(committed_sessions, k8s_settings, apiserver, sid)
    spec = apiserver.jobs[(NAMESPACE, job_name(sid, 1))]["spec"]
    assert (spec["completionMode"], spec["completions"], spec["parallelism"]) == ("Indexed", 3, 3)
    apiserver.fail(NAMESPACE, job_name(sid, 1))
    assert run.wait() == State.ERROR


def test_a_policy_log_that_is_not_utf8_does_not_cost_the_result(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    plan = plan_of(committed_sessions, k8s_settings, sid)
    abort = Abort(kind="policy_error", reason="the policy raised: boom")
    document = build_result(plan, "image", [ShardOutcome(abort=(0, 0, abort))], started=STARTED)
    garbage = "bad bytes: \udcff\udcfe\n"  # b"\xff\xfe" on the wire
    apiserver.succeed(NAMESPACE, name, [printed(document)], policy_logs=[garbage])
    assert run.wait() == State.FAILED
    assert run.submission(sid).log_tail == "bad bytes: \ufffd\ufffd"


def test_a_young_job_of_an_attempt_not_yet_seen_active_is_kept(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, queued.id)
    now = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    apiserver.jobs[(NAMESPACE, name)]["metadata"]["creationTimestamp"] = now
    (clean,) = runtime_cleaners(k8s_settings)
    assert clean(set()) == []  # just created: the reconciler's snapshot may predate it
    apiserver.fail(NAMESPACE, name)
    assert run.wait() == State.ERROR


def test_a_job_of_the_same_name_that_is_not_ours_is_left_alone(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    other = build_job(make_spec(submission_id=queued.id, attempt=1))
    other["metadata"]["labels"]["manieval.io/submission"] = "999"
    apiserver.put_job(other)
    assert Run(committed_sessions, k8s_settings).wait() == State.ERROR
    with committed_sessions() as db:
        submission = db.get(Submission, queued.id)
        assert submission is not None
        assert submission.reason.startswith("cannot create the evaluation Job")
    assert apiserver.deletions == []
    assert (NAMESPACE, job_name(queued.id, 1)) in apiserver.jobs


def test_a_bug_while_watching_still_ends_the_attempt_and_removes_the_job(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def broken(*_args: object) -> None:
        raise RuntimeError("unexpected")

    monkeypatch.setattr(KubernetesExecutor, "pods", broken)
    name = job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, queued.id)
    assert run.wait() == State.ERROR
    assert run.submission(queued.id).reason == "the worker failed: RuntimeError: unexpected"
    assert (name, "Foreground") in apiserver.deletions


def test_a_lost_watcher_is_replaced_and_the_running_job_kept(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:

    sid, name = queued.id, job_name(queued.id, 1)
    with committed_sessions() as db:
        assert claim_next(db, max_running_per_user=2) == (sid, 1)
        submission = db.get(Submission, sid)
        assert submission is not None
        setup = {
            "suite": suite_of(submission.challenge),
            "suite_yaml": submission.challenge.suite_yaml,
            "phase": "dev",
            "pinned": submission.pinned_image,
        }
    killed = threading.Event()  # the first watcher's worker dies once the Job exists
    first = threading.Thread(
        target=run_as_job,
        args=(committed_sessions, k8s_settings, sid, 1),
        kwargs=setup | {"stop": killed},
    )
    first.start()
    until(lambda: (NAMESPACE, name) in apiserver.jobs, "the Job")
    killed.set()
    first.join(timeout=30)
    apiserver.run(NAMESPACE, name)

    sent: list[tuple[int, int]] = []

    def send(submission_id: int, attempt: int) -> None:
        sent.append((submission_id, attempt))

    later = utcnow() + timedelta(minutes=4)  # past the heartbeat timeout
    report = reconcile(
        committed_sessions,
        RecordingQueue(),
        resume=job_resumer(k8s_settings, send),
        now=later,
    )
    assert (report.resumed, report.lost, sent) == ([sid], [], [(sid, 1)])
    assert Run(committed_sessions, k8s_settings).submission(sid).state == State.RUNNING

    outcome: list[State | None] = []
    second = threading.Thread(
        target=lambda: outcome.append(resume_watch(committed_sessions, k8s_settings, sid, 1))
    )
    second.start()
    plan = plan_of(committed_sessions, k8s_settings, sid)
    document = build_result(plan, "image", [ShardOutcome()], started=STARTED)
    apiserver.succeed(NAMESPACE, name, [printed(document)])
    second.join(timeout=60)
    assert outcome == [State.SUCCEEDED]
    assert [d for d in apiserver.deletions if d[0] == name] == [(name, "Foreground")]


def test_a_silent_attempt_whose_job_is_gone_is_lost_as_before(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:

    with committed_sessions.begin() as db:
        assert report_state(db, queued.id, 1, State.LAUNCHING, "go")
        assert report_state(db, queued.id, 1, State.RUNNING, "go")
    sent: list[tuple[int, int]] = []
    later = utcnow() + timedelta(minutes=4)
    resume = job_resumer(k8s_settings, lambda sid, attempt: sent.append((sid, attempt)))
    report = reconcile(committed_sessions, RecordingQueue(), resume=resume, now=later)
    assert (report.resumed, report.lost, sent) == ([], [queued.id], [])


def test_an_eviction_that_makes_the_job_run_out_of_time_is_not_the_policys_fault(
    committed_sessions: sessionmaker[Session],
    k8s_settings: Settings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(committed_sessions, k8s_settings, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    apiserver.disrupt(NAMESPACE, name)  # the replacement pod starts late...
    apiserver.exceed_deadline(NAMESPACE, name)  # ...and the Job's clock ran on
    assert run.wait() == State.ERROR  # ours: it does not count against the quota
    assert "evicted" in run.submission(queued.id).reason
