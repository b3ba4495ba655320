"""The worker with `executor=kubernetes`: a submission becomes a Job, is watched, and ends.

The official client talks over HTTP to the API-server double; the tests play the Job
controller and the kubelet. In the end-to-end test the "kubelet" really runs the pod: the
evaluator entry point with the env the Job manifest gives it, and the scripted policy next to it.
"""

from __future__ import annotations

import base64
import json
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
from sqlalchemy import Engine, select, update
from sqlalchemy.orm import Session, joinedload, sessionmaker

from evaluator.evaluation import build_result, evaluate
from evaluator.job import JOB_SPEC_FILE_ENV, evaluation_job, write_document
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import Abort, EvaluationResult, episode_records
from evaluator.runner import ShardOutcome
from evaluator.sources import LocalDirectory
from evaluator.suite import SUITES_DIR
from internal_api.schemas import State
from server.challenges.service import ChallengeOptions, load_challenge, suite_of
from server.kit.settings import Settings
from server.models import Cause, Submission, Transition, utcnow
from server.submissions.service import cancel
from testkit.factories import SUITE, make_challenge, make_user, queue_submission
from testkit.k8s_double import (
    CONTROLLERS,
    EVALUATOR_IMAGE,
    NAMESPACE,
    ApiServerDouble,
    running_apiserver,
)
from testkit.waiting import until
from testkit.workers import worker_settings
from tests.evaluator.conftest import REPO, SCRIPTED
from tests.worker.k8s_specs import (
    make_spec,
)
from worker.kubernetes import informer as informer_module
from worker.kubernetes import watch as watch_module
from worker.kubernetes.client import Backoff
from worker.kubernetes.informer import running_watch
from worker.kubernetes.manifest import build_job, job_name
from worker.kubernetes.spec import job_spec
from worker.kubernetes.watch import resume_watch, run_as_job
from worker.reconcile import job_resumer, reconcile_pass, runtime_cleaners
from worker.run import run_next
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

pytestmark = pytest.mark.long

STARTED = datetime(2026, 5, 1, tzinfo=UTC)


@pytest.fixture
def apiserver(engine: Engine) -> Iterator[ApiServerDouble]:
    """The double, its Job controller ending Jobs in the order of one version (1.29, 1.31+)
    per database backend. The two are independent (the double never reads the database, the
    server never sees the controller), so each test runs once with each version and once on
    each backend, rather than through all four pairs."""
    by_backend = dict(zip(("sqlite", "postgresql"), CONTROLLERS, strict=True))
    with running_apiserver(by_backend[engine.dialect.name]) as double:
        yield double


def k8s_worker(
    settings: Settings, apiserver: ApiServerDouble, **overrides: object
) -> WorkerSettings:
    """A worker whose executor is the API-server double's cluster."""
    values: dict[str, object] = {
        "executor": "kubernetes",
        "k8s_api_url": apiserver.host,
        "k8s_namespace": NAMESPACE,
        "evaluator_image": EVALUATOR_IMAGE,
        "k8s_poll_interval": 0.05,
        "k8s_progress_interval": 0.05,
    }
    return worker_settings(settings, **(values | overrides))


@pytest.fixture
def wsettings(settings: Settings, apiserver: ApiServerDouble) -> WorkerSettings:
    """Overrides the worker fixture: the `api` fixture is this worker's client."""
    return k8s_worker(settings, apiserver)


class Run:
    """`run_next` in a thread, as a Celery task would run it; reads what the server recorded."""

    def __init__(
        self, api: ServerAPI, wsettings: WorkerSettings, sessions: sessionmaker[Session]
    ) -> None:
        self.sessions = sessions
        self.outcome: tuple[int, State | None] | None = None
        self.thread = threading.Thread(target=self._run, args=(api, wsettings), daemon=True)
        self.thread.start()

    def _run(self, api: ServerAPI, wsettings: WorkerSettings) -> None:
        self.outcome = run_next(api, wsettings)

    def wait(self) -> State | None:
        self.thread.join(timeout=120)
        assert not self.thread.is_alive(), "the worker did not end the attempt"
        assert self.outcome is not None
        return self.outcome[1]

    def submission(self, sid: int) -> Submission:
        return submission_of(self.sessions, sid)


def submission_of(sessions: sessionmaker[Session], sid: int) -> Submission:
    with sessions() as db:
        submission = db.get(Submission, sid)
        assert submission is not None
        return submission


def attempt_end(sessions: sessionmaker[Session], sid: int, attempt: int = 1) -> Transition:
    """How the attempt ended: its transition to a final state (kept when it runs again)."""
    with sessions() as db:
        ends = [
            t
            for t in db.scalars(select(Transition).where(Transition.submission_id == sid))
            if t.attempt == attempt and t.to_state.final
        ]
        assert len(ends) == 1, ends
        return ends[0]


def assert_cluster_error(sessions: sessionmaker[Session], sid: int, state: State | None) -> str:
    """The cluster's doing: attempt 1 ended `error` with the cluster's cause, and the
    submission runs again as attempt 2 (no quota used). Returns attempt 1's reason."""
    assert state == State.QUEUED
    end = attempt_end(sessions, sid)
    assert (end.to_state, end.cause) == (State.ERROR, Cause.CLUSTER)
    assert end.reason.endswith("; queued again"), end.reason
    submission = submission_of(sessions, sid)
    assert (submission.state, submission.attempt) == (State.QUEUED, 2)
    return end.reason


@pytest.fixture
def queued(committed_sessions: sessionmaker[Session]) -> Submission:
    with committed_sessions() as db:
        challenge = make_challenge(db, quota_concurrent=10, quota_per_day=10)
        submission = queue_submission(db, make_user(db, "alice"), challenge)
        db.commit()
        return submission


def start(
    api: ServerAPI,
    wsettings: WorkerSettings,
    sessions: sessionmaker[Session],
    apiserver: ApiServerDouble,
    sid: int,
) -> Run:
    run = Run(api, wsettings, sessions)
    until(lambda: (NAMESPACE, job_name(sid, 1)) in apiserver.jobs, "the Job")
    until(lambda: (NAMESPACE, f"{job_name(sid, 1)}-evaluation") in apiserver.secrets, "its Secret")
    assert run.submission(sid).state == State.RUNNING
    return run


def a_worker_dies(
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    sid: int,
    *,
    watching: bool = True,
    meanwhile: Callable[[], object] = lambda: None,
) -> None:
    """A worker claims attempt 1 of `sid` and creates its Job (and, where `watching`, watches
    it); `meanwhile` happens; then the worker's process goes, and its watch with it."""
    handed = api.claim(wsettings.worker_name)
    assert handed is not None
    assert (handed.submission_id, handed.attempt) == (sid, 1)
    killed = threading.Event()
    first = threading.Thread(
        target=run_as_job, args=(api, wsettings, handed), kwargs={"stop": killed}
    )
    first.start()
    until(lambda: (NAMESPACE, job_name(sid, 1)) in apiserver.jobs, "the Job")
    if watching:
        until(lambda: running_watch(wsettings) is not None, "the worker's watch")
    meanwhile()
    killed.set()
    first.join(timeout=30)
    assert not first.is_alive()
    assert running_watch(wsettings) is None


def silent_for(sessions: sessionmaker[Session], sid: int, minutes: float) -> None:
    """Let time pass for the server: the attempt's worker last reported `minutes` ago."""
    long_ago = utcnow() - timedelta(minutes=minutes)
    with sessions.begin() as db:
        db.execute(
            update(Submission)
            .where(Submission.id == sid)
            .values(heartbeat_at=long_ago, updated_at=long_ago)
        )


def plan_of(sessions: sessionmaker[Session], settings: Settings, sid: int) -> EvaluationPlan:
    with sessions() as db:
        submission = db.get(Submission, sid, options=[joinedload(Submission.challenge)])
        assert submission is not None
        suite = suite_of(submission.challenge)
    return build_plan(suite, "dev", secret=settings.secret("seed_secret").encode())


def printed(document: EvaluationResult) -> str:
    out = tempfile.SpooledTemporaryFile(mode="w+")
    write_document(document, out)
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
        # The Secret volume, as the kubelet mounts it into the evaluator container alone.
        secret_file = Path(env[JOB_SPEC_FILE_ENV])
        (mount,) = [
            m for m in evaluator["volumeMounts"] if m["mountPath"] == str(secret_file.parent)
        ]
        (volume,) = [
            v for v in manifest["spec"]["template"]["spec"]["volumes"] if v["name"] == mount["name"]
        ]
        secret = apiserver.secrets[(NAMESPACE, volume["secret"]["secretName"])]
        mounted = endpoint / "secret"
        mounted.mkdir()
        (mounted / secret_file.name).write_bytes(base64.b64decode(secret["data"][secret_file.name]))
        env[JOB_SPEC_FILE_ENV] = str(mounted / secret_file.name)
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
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
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
    local = evaluate(plan_of(committed_sessions, settings, sid), LocalDirectory(SCRIPTED))
    assert episode_records(result) == episode_records(local)
    assert (name, "Foreground") in apiserver.deletions  # collected, then deleted


def test_the_job_is_built_from_the_plan_and_the_settings(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sized = k8s_worker(
        settings, apiserver, k8s_runtime_class="gvisor", policy_cpus=0.5, policy_memory_mib=768
    )
    run = start(api, sized, committed_sessions, apiserver, queued.id)
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
    secret = apiserver.secrets[(NAMESPACE, f"{job_name(queued.id, 1)}-evaluation")]
    document = base64.b64decode(secret["data"]["evaluation.json"]).decode()
    assert secret["metadata"]["ownerReferences"][0]["uid"] == manifest["metadata"]["uid"]
    plan = plan_of(committed_sessions, settings, queued.id)
    with committed_sessions() as db:
        submission = db.get(Submission, queued.id, options=[joinedload(Submission.challenge)])
        assert submission is not None
        suite_yaml = submission.challenge.suite_yaml
    assert document == evaluation_job(plan, suite_yaml=suite_yaml).canonical_json()
    assert document not in json.dumps(manifest)  # the seeds are in no Job object...
    apiserver.run(NAMESPACE, job_name(queued.id, 1))
    for pod_object in apiserver.pods_of(NAMESPACE, job_name(queued.id, 1)):
        assert document not in json.dumps(pod_object)  # ...nor in any Pod object
        assert '"seeds"' not in json.dumps(pod_object)
    apiserver.fail(NAMESPACE, job_name(queued.id, 1))
    run.wait()
    assert apiserver.secrets == {}  # deleted with its Job


def test_a_policy_abort_fails_the_submission_with_the_pods_reason_and_log(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    apiserver.policy_killed(NAMESPACE, name)
    plan = plan_of(committed_sessions, settings, sid)
    abort = Abort(kind="policy_crashed", reason="the policy disconnected")
    outcome = ShardOutcome(episodes=[], abort=(0, 0, abort))
    document = build_result(plan, "image", [outcome], started=STARTED)
    apiserver.succeed(NAMESPACE, name, [printed(document)], policy_logs=["Killed\n"])
    assert run.wait() == State.FAILED
    submission = run.submission(sid)
    assert submission.reason == (  # as the sandbox and the container engine name it
        "the policy disconnected (Kubernetes stopped it at its memory limit of 2048 MiB)"
    )
    assert submission.log_tail == "Killed"
    with committed_sessions() as db:
        stored = db.get(Submission, sid)
        assert stored is not None
        assert stored.result is not None
        assert stored.result["abort"]["kind"] == "memory_limit"


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
            State.QUEUED,  # the deadline covers the whole plan: the cluster's doing
            "the cluster stopped the evaluation: its Job ran past its deadline (DeadlineExceeded",
        ),
        (
            # From 1.31 the pods go before the Job says Failed: its FailureTarget decides
            lambda api, name: (
                api.exceed_deadline(NAMESPACE, name),
                api.settle(NAMESPACE, name, terminal=False),
            ),
            State.QUEUED,
            "the cluster stopped the evaluation: its Job ran past its deadline (DeadlineExceeded",
        ),
        (
            lambda api, name: api.jobs.pop((NAMESPACE, name)),
            State.QUEUED,  # the cluster's doing: it runs again
            "the evaluation's Job eval-",
        ),
        (
            lambda api, name: api.succeed(NAMESPACE, name, ["no result here\n"]),
            State.ERROR,
            "the evaluation's result could not be read",
        ),
    ],
    ids=[
        "evaluator-failed",
        "deadline",
        "deadline-pods-gone-first",
        "job-vanished",
        "unreadable",
    ],
)
def test_every_way_a_job_ends_gives_a_final_state_with_a_reason(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
    arrange: Callable[[ApiServerDouble, str], object],
    state: State,
    reason: str,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name, ready=False)
    arrange(apiserver, name)
    assert run.wait() == state
    assert attempt_end(committed_sessions, queued.id).reason.startswith(reason)


def test_an_evaluator_out_of_memory_is_the_services_sizing_never_the_policys(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    message = "Container evaluator for pod x failed with exit code 137"
    apiserver.fail(NAMESPACE, name, message=message, evaluator_oom=True)
    reason = assert_cluster_error(committed_sessions, queued.id, run.wait())
    assert reason.startswith(
        "the cluster stopped the evaluation: the evaluator ran out of memory (its limit of "
        "4096 MiB: raise MANIEVAL_EVALUATOR_MEMORY)"
    )


def test_cancel_during_a_run_deletes_the_job_and_its_pods(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    with committed_sessions.begin() as db:
        submission = db.get(Submission, queued.id, options=[joinedload(Submission.user)])
        assert submission is not None
        cancel(db, submission.user, submission)
    assert run.wait() == State.CANCELLED
    assert (name, "Foreground") in apiserver.deletions
    assert apiserver.pods_of(NAMESPACE, name) == []


def test_a_missing_evaluator_image_is_a_configuration_error(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    unconfigured = k8s_worker(settings, apiserver, evaluator_image=None)
    assert Run(api, unconfigured, committed_sessions).wait() == State.ERROR
    with committed_sessions() as db:
        submission = db.get(Submission, queued.id)
        assert submission is not None
        assert "MANIEVAL_EVALUATOR_IMAGE" in submission.reason
    assert apiserver.jobs == {}


def test_the_reconciler_deletes_jobs_of_attempts_no_longer_active(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    (clean,) = runtime_cleaners(wsettings)
    assert clean({(queued.id, 1)}) == []  # active: kept
    assert clean(set()) == [name]  # e.g. its worker died and the attempt was ended
    state = run.wait()  # the worker watching it sees it gone, and says so: not the policy's
    assert "disappeared" in assert_cluster_error(committed_sessions, queued.id, state)


def queue_sharded(committed_sessions: sessionmaker[Session], tmp_path: Path) -> int:
    """A queued submission to a challenge whose suite asks for 3 shards."""
    sharded = tmp_path / "sharded.yaml"
    sharded.write_text(SUITE.read_text().replace("name: server-tiny", "name: sharded\nshards: 3"))
    with committed_sessions() as db:
        options = ChallengeOptions(quota_concurrent=10, quota_per_day=10)
        challenge = load_challenge(db, sharded, options, seed_secret="s" * 32)
        sid = queue_submission(db, make_user(db, "bob"), challenge).id
        db.commit()
    return sid


def test_a_suite_that_asks_for_shards_gets_an_indexed_job(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    tmp_path: Path,
) -> None:
    sid = queue_sharded(committed_sessions, tmp_path)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    spec = apiserver.jobs[(NAMESPACE, job_name(sid, 1))]["spec"]
    assert (spec["completionMode"], spec["completions"], spec["parallelism"]) == ("Indexed", 3, 3)
    apiserver.fail(NAMESPACE, job_name(sid, 1))
    assert run.wait() == State.ERROR


def test_a_policy_log_that_is_not_utf8_does_not_cost_the_result(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    plan = plan_of(committed_sessions, settings, sid)
    abort = Abort(kind="policy_error", reason="the policy raised: boom")
    document = build_result(plan, "image", [ShardOutcome(abort=(0, 0, abort))], started=STARTED)
    garbage = "bad bytes: \udcff\udcfe\n"  # b"\xff\xfe" on the wire
    apiserver.succeed(NAMESPACE, name, [printed(document)], policy_logs=[garbage])
    assert run.wait() == State.FAILED
    assert run.submission(sid).log_tail == "bad bytes: \ufffd\ufffd"


def test_a_young_job_of_an_attempt_not_yet_seen_active_is_kept(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    now = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    apiserver.jobs[(NAMESPACE, name)]["metadata"]["creationTimestamp"] = now
    (clean,) = runtime_cleaners(wsettings)
    assert clean(set()) == []  # just created: the reconciler's snapshot may predate it
    apiserver.fail(NAMESPACE, name)
    assert run.wait() == State.ERROR


def test_a_job_of_the_same_name_that_is_not_ours_is_left_alone(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    other = build_job(make_spec(submission_id=queued.id, attempt=1))
    other["metadata"]["labels"]["manieval.io/submission"] = "999"
    apiserver.put_job(other)
    assert Run(api, wsettings, committed_sessions).wait() == State.ERROR
    with committed_sessions() as db:
        submission = db.get(Submission, queued.id)
        assert submission is not None
        assert submission.reason.startswith("cannot create the evaluation Job")
    assert apiserver.deletions == []
    assert (NAMESPACE, job_name(queued.id, 1)) in apiserver.jobs


def test_a_bug_while_watching_still_ends_the_attempt_and_removes_the_job(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def broken(*_args: object) -> None:
        raise RuntimeError("unexpected")

    monkeypatch.setattr(watch_module, "pod_view", broken)
    name = job_name(queued.id, 1)
    run = Run(api, wsettings, committed_sessions)  # the Job may end before a look at it
    assert run.wait() == State.ERROR
    assert run.submission(queued.id).reason == "the worker failed: RuntimeError: unexpected"
    assert (name, "Foreground") in apiserver.deletions


def test_a_lost_watcher_is_replaced_and_the_running_job_kept(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    a_worker_dies(api, wsettings, apiserver, sid, watching=False)  # once the Job exists
    apiserver.run(NAMESPACE, name)
    silent_for(committed_sessions, sid, minutes=4)  # past the heartbeat timeout
    assert [(r.submission_id, r.attempt) for r in api.silent()] == [(sid, 1)]

    sent: list[tuple[int, int]] = []

    def send(submission_id: int, attempt: int) -> None:
        sent.append((submission_id, attempt))

    report = reconcile_pass(
        api, cleaners=runtime_cleaners(wsettings), resume=job_resumer(wsettings, send)
    )
    assert (report.resumed, report.server.lost, sent) == ([sid], [], [(sid, 1)])
    assert report.removed == []  # its Job belongs to an active attempt: kept
    assert (NAMESPACE, name) in apiserver.jobs
    assert submission_of(committed_sessions, sid).state == State.RUNNING
    assert api.silent() == []  # heartbeat given until the new watcher looks

    outcome: list[State | None] = []
    second = threading.Thread(target=lambda: outcome.append(resume_watch(api, wsettings, sid, 1)))
    second.start()
    plan = plan_of(committed_sessions, settings, sid)
    document = build_result(plan, "image", [ShardOutcome()], started=STARTED)
    apiserver.succeed(NAMESPACE, name, [printed(document)])
    second.join(timeout=60)
    assert outcome == [State.SUCCEEDED]
    assert submission_of(committed_sessions, sid).state == State.SUCCEEDED
    assert [d for d in apiserver.deletions if d[0] == name] == [(name, "Foreground")]


def test_a_silent_attempt_whose_job_is_gone_is_lost_as_before(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    queued: Submission,
) -> None:
    handed = api.claim(wsettings.worker_name)  # claimed and running, but no Job was made
    assert handed is not None
    running = api.running(queued.id, 1, reason="go", deadline_s=3600)
    assert running is not None
    assert running.applied
    silent_for(committed_sessions, queued.id, minutes=4)
    sent: list[tuple[int, int]] = []
    resume = job_resumer(wsettings, lambda sid, attempt: sent.append((sid, attempt)))
    report = reconcile_pass(api, cleaners=runtime_cleaners(wsettings), resume=resume)
    assert (report.resumed, report.server.lost, sent) == ([], [queued.id], [])
    assert report.server.requeued == [queued.id]  # our fault, the first time: it runs again
    submission = submission_of(committed_sessions, queued.id)
    assert (submission.state, submission.attempt) == (State.QUEUED, 2)


def test_an_eviction_then_the_deadline_passing_is_still_the_evictions_doing(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    with apiserver.together():
        apiserver.disrupt(NAMESPACE, name)  # FailJob: the Job fails, no pod replaces it...
        apiserver.exceed_deadline(NAMESPACE, name)  # ...so its clock running on changes nothing
    reason = assert_cluster_error(committed_sessions, queued.id, run.wait())
    assert "(EvictionByEvictionAPI" in reason, reason
    assert "deadline" not in reason


@pytest.mark.parametrize(
    "disruption",
    ["EvictionByEvictionAPI", "PreemptionByScheduler"],
    ids=["evicted-or-drained", "preempted"],
)
def test_a_restarted_worker_that_missed_the_eviction_reads_the_jobs_failure_as_the_clusters(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
    disruption: str,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    a_worker_dies(api, wsettings, apiserver, sid, meanwhile=lambda: apiserver.run(NAMESPACE, name))
    apiserver.evict(NAMESPACE, name, reason=disruption)  # a drain or a preemption meanwhile
    assert apiserver.pods_of(NAMESPACE, name) == []  # the eviction is lost: only the Job is left

    outcome: list[State | None] = []
    second = threading.Thread(target=lambda: outcome.append(resume_watch(api, wsettings, sid, 1)))
    second.start()
    second.join(timeout=60)
    assert not second.is_alive()
    # error, cause cluster, queued again as attempt 2: no quota used
    reason = assert_cluster_error(committed_sessions, sid, *outcome)
    assert "was disrupted by the cluster, which failed its Job (PodFailurePolicy: Pod " in reason
    assert "has condition DisruptionTarget matching FailJob rule at index 0" in reason


@pytest.fixture
def core_queued(committed_sessions: sessionmaker[Session]) -> Submission:
    """A submission to the core suite: a 2 h budget, and its evaluator's own time besides."""
    with committed_sessions() as db:
        options = ChallengeOptions(quota_concurrent=10, quota_per_day=10)
        challenge = load_challenge(
            db, SUITES_DIR / "maniskill-core.yaml", options, seed_secret="s" * 32
        )
        submission = queue_submission(db, make_user(db, "carol"), challenge)
        db.commit()
        return submission


def test_a_policy_using_its_whole_budget_on_a_slow_evaluator_is_not_killed_by_the_deadline(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    core_queued: Submission,
) -> None:
    """The policy's answers take its whole budget and the evaluator's own work a fifth of it
    more, after ten minutes of scheduling and pulls: the Job's deadline covers all of it (it
    counts from the Job's start, the policy's budget only the answers)."""
    sid, name = core_queued.id, job_name(core_queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    budget = plan_of(committed_sessions, settings, sid).limits.budget_s
    apiserver.advance(600)  # the node, the images
    apiserver.run(NAMESPACE, name)
    apiserver.advance(budget * 1.2)
    assert "conditions" not in apiserver.jobs[(NAMESPACE, name)]["status"]  # not killed
    apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
    assert run.wait() == State.SUCCEEDED


def test_a_job_the_cluster_kills_at_its_deadline_is_the_clusters_doing(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    """The deadline holds the whole plan's wall-clock limit and the start-up: a Job that the
    controller still kills there was slowed by the cluster (`error`, cause `cluster`, no quota
    used, run once more), while the evaluator's own `budget_exhausted` stays `timed_out`."""
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    deadline = apiserver.jobs[(NAMESPACE, name)]["spec"]["activeDeadlineSeconds"]
    apiserver.advance(deadline)
    reason = assert_cluster_error(committed_sessions, queued.id, run.wait())
    assert "ran past its deadline (DeadlineExceeded" in reason, reason


def looked_twice(
    apiserver: ApiServerDouble,
    wsettings: WorkerSettings,
    sessions: sessionmaker[Session],
    sid: int,
) -> None:
    """Wait until the watcher has seen what the double holds now: the process's watch has
    every change, and the watcher has beaten twice since (it looks before it beats)."""

    def caught_up() -> bool:
        watch = running_watch(wsettings)
        return watch is not None and all(
            apiserver.caught_up(informer.resource_version, informer.kind)
            for informer in (watch.jobs, watch.pods)
        )

    until(caught_up, "the watch to see every change")
    for _ in range(2):
        before = submission_of(sessions, sid).heartbeat_at
        until(lambda b=before: submission_of(sessions, sid).heartbeat_at != b, "a heartbeat")


def test_a_job_the_quota_refuses_ends_error_at_once_with_the_clusters_reason(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    apiserver.job_quota = 0
    apiserver.quotas_readable = False  # so the worker cannot see it coming
    reason = assert_cluster_error(
        committed_sessions, queued.id, Run(api, wsettings, committed_sessions).wait()
    )
    assert "cannot create the evaluation Job: 403" in reason
    assert "exceeded quota: eval-quota" in reason
    assert apiserver.jobs == {}


def test_a_job_no_quota_could_ever_hold_ends_error_without_creating_it(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    apiserver.job_quota = 0
    assert Run(api, wsettings, committed_sessions).wait() == State.ERROR  # ours, not again
    end = attempt_end(committed_sessions, queued.id)
    assert end.cause is None
    assert end.reason == (
        "cannot run on this cluster: quota eval-quota allows count/jobs.batch=0, "
        "less than one evaluation Job needs (1)"
    )
    assert [r for r in apiserver.requests if r.method == "POST"] == []


@pytest.mark.parametrize(
    ("pod_quota", "controller", "expected"),
    [
        (
            None,
            lambda api, ns, name: api.unschedulable(ns, name),
            "its pod could not be scheduled in 1 s: 0/3 nodes are available: "
            "3 Insufficient nvidia.com/gpu.",
        ),
        (
            0,
            lambda api, ns, name: api.run(ns, name),
            "no pod was created in 1 s: FailedCreate: Error creating: pods",
        ),
        (None, lambda api, ns, name: None, "no pod was created in 1 s"),
        (None, lambda api, ns, name: api.run(ns, name, ready=False), "its pod stayed pending"),
    ],
    ids=["unschedulable", "pods-refused-by-quota", "no-pod-at-all", "pending"],
)
def test_pods_that_never_run_end_error_after_the_pending_timeout_not_the_deadline(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
    pod_quota: int | None,
    controller: Callable[[ApiServerDouble, str, str], object],
    expected: str,
) -> None:
    apiserver.pod_quota = pod_quota
    apiserver.quotas_readable = False  # else the worker waits for room instead
    apiserver.on_create = lambda ns, name: controller(apiserver, ns, name)
    patient = k8s_worker(settings, apiserver, k8s_pending_timeout_s=0.5)
    state = Run(api, patient, committed_sessions).wait()
    reason = assert_cluster_error(committed_sessions, queued.id, state)
    prefix = "the cluster stopped the evaluation: "
    assert reason.startswith(prefix + expected.split(" 1 s")[0]), reason
    assert expected.split(" 1 s")[-1] in reason
    if pod_quota is not None:
        assert "exceeded quota: eval-quota" in reason
    assert apiserver.jobs == {}  # deleted: the deadline (900 s) was never waited for


def test_a_pod_pending_within_the_timeout_is_waited_for(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.unschedulable(NAMESPACE, name)  # the autoscaler adds a node in time...
    looked_twice(apiserver, wsettings, committed_sessions, queued.id)
    assert run.submission(queued.id).state == State.RUNNING
    apiserver.exceed_deadline(NAMESPACE, name)  # ...or not: then the deadline decides
    assert_cluster_error(committed_sessions, queued.id, run.wait())


@pytest.mark.parametrize(
    ("disrupt", "expected"),
    [
        (lambda api, name: api.evict(NAMESPACE, name), "which failed its Job (PodFailurePolicy"),
        (
            lambda api, name: api.evict(NAMESPACE, name, reason="PreemptionByScheduler"),
            "which failed its Job (PodFailurePolicy",
        ),
        (lambda api, name: api.disrupt(NAMESPACE, name), "(EvictionByEvictionAPI"),
        (lambda api, name: api.lose_node(NAMESPACE, name), "(DeletionByTaintManager"),
    ],
    ids=["evicted-and-deleted", "preempted", "evicted-kept-listed", "node-lost"],
)
def test_a_pod_the_cluster_evicts_or_loses_ends_error_at_once_with_its_reason(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
    disrupt: Callable[[ApiServerDouble, str], object],
    expected: str,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    looked_twice(apiserver, wsettings, committed_sessions, queued.id)
    disrupt(apiserver, name)  # ours: no quota used, run again, long before the deadline
    reason = assert_cluster_error(committed_sessions, queued.id, run.wait())
    assert reason.startswith("the cluster stopped the evaluation: pod eval-"), reason
    assert expected in reason
    assert apiserver.jobs == {}


def test_one_shard_left_unschedulable_ends_the_attempt_after_the_pending_timeout(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    tmp_path: Path,
) -> None:
    sid = queue_sharded(committed_sessions, tmp_path)

    def two_of_three_scheduled(namespace: str, name: str) -> None:
        pods = apiserver.run(namespace, name)  # all three start...
        last = apiserver.pods[(namespace, pods[2])]
        last["status"] = {  # ...but the third: no node has room for it
            "phase": "Pending",
            "conditions": [
                {
                    "type": "PodScheduled",
                    "status": "False",
                    "reason": "Unschedulable",
                    "message": "0/3 nodes are available: 3 Insufficient cpu.",
                }
            ],
        }

    apiserver.on_create = two_of_three_scheduled
    patient = k8s_worker(settings, apiserver, k8s_pending_timeout_s=0.5)
    reason = assert_cluster_error(
        committed_sessions, sid, Run(api, patient, committed_sessions).wait()
    )
    assert reason.startswith("the cluster stopped the evaluation: its pod could not be scheduled")
    assert reason.endswith("3 Insufficient cpu.; queued again")


def test_a_resumed_watch_gives_the_job_its_secret_if_its_creator_died_before(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    handed = api.claim(wsettings.worker_name)
    assert handed is not None
    assert api.running(sid, 1, reason="evaluating", deadline_s=900) is not None
    apiserver.put_job(build_job(job_spec(wsettings, handed)))  # the creator died right after
    assert apiserver.secrets == {}
    outcome: list[State | None] = []
    watcher = threading.Thread(target=lambda: outcome.append(resume_watch(api, wsettings, sid, 1)))
    watcher.start()
    until(lambda: (NAMESPACE, f"{name}-evaluation") in apiserver.secrets, "the Secret")
    secret = apiserver.secrets[(NAMESPACE, f"{name}-evaluation")]
    assert (
        secret["metadata"]["ownerReferences"][0]["uid"]
        == (apiserver.jobs[(NAMESPACE, name)]["metadata"]["uid"])
    )
    plan = plan_of(committed_sessions, settings, sid)
    document = build_result(plan, "image", [ShardOutcome()], started=STARTED)
    apiserver.succeed(NAMESPACE, name, [printed(document)])
    watcher.join(timeout=60)
    assert outcome == [State.SUCCEEDED]


def cancel_now(sessions: sessionmaker[Session], sid: int) -> None:
    with sessions.begin() as db:
        submission = db.get(Submission, sid, options=[joinedload(Submission.user)])
        assert submission is not None
        cancel(db, submission.user, submission)


def states(sessions: sessionmaker[Session], sids: list[int]) -> list[State]:
    return [submission_of(sessions, sid).state for sid in sids]


def waiting_for_room(sessions: sessionmaker[Session], sid: int) -> bool:
    submission = submission_of(sessions, sid)
    phase = (submission.progress or {}).get("phase")
    return submission.state == State.LAUNCHING and phase == "waiting for room in the cluster"


def test_a_rollout_never_runs_more_jobs_than_the_quota_holds(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
) -> None:
    """Draining and new workers side by side, more of them than the quota has pods for: the
    extra claims wait for room instead of creating Jobs whose pods the quota would refuse."""
    with committed_sessions() as db:
        challenge = make_challenge(db, quota_concurrent=10, quota_per_day=10)
        users = [make_user(db, f"user{i}") for i in range(4)]
        sids = [queue_submission(db, user, challenge).id for user in users]
        db.commit()
    apiserver.pod_quota = 2
    live: list[int] = []

    def controller(namespace: str, name: str) -> None:
        apiserver.run(namespace, name)
        live.append(apiserver._live_pods(namespace))

    apiserver.on_create = controller
    draining = k8s_worker(settings, apiserver, worker_name="worker-old")
    new = k8s_worker(settings, apiserver, worker_name="worker-new")
    runs = []
    for claimed, ws in enumerate((draining, new, draining, new), start=1):
        runs.append(Run(api, ws, committed_sessions))  # one claim after another, as they come
        until(
            lambda n=claimed: states(committed_sessions, sids).count(State.QUEUED) == 4 - n,
            "a claim",
        )
        until(lambda n=claimed: len(apiserver.jobs) == min(n, 2), "its Job, while there is room")
    until(
        lambda: sum(waiting_for_room(committed_sessions, sid) for sid in sids) == 2,
        "the other two claims waiting for room",
    )
    names = {job_name(sid, 1): sid for sid in sids}
    succeeded: set[str] = set()
    deadline = time.monotonic() + 120
    while len(succeeded) < len(sids):
        assert time.monotonic() < deadline, f"only {sorted(succeeded)} ran"
        with apiserver.lock:
            created = [name for (_, name) in apiserver.jobs if name not in succeeded]
        for name in created:
            plan = plan_of(committed_sessions, settings, names[name])
            document = build_result(plan, "image", [ShardOutcome()], started=STARTED)
            apiserver.succeed(NAMESPACE, name, [printed(document)])
            succeeded.add(name)
        time.sleep(0.02)
    assert [run.wait() for run in runs] == [State.SUCCEEDED] * 4
    assert max(live) <= 2
    # Two workers may see the same room at once (a look at the quotas, then a create; on a
    # busy machine it happens): the quota refuses the later Job's pods, and its worker takes
    # the Job back and makes it again once there is room (`_make_room`). Whatever the timing,
    # all four ran and never more pods than the quota holds; a refusal is the quota's only.
    refused = [e for e in apiserver.events if e.get("reason") == "FailedCreate"]
    assert all("exceeded quota" in e["message"] for e in refused), refused


def test_a_cancel_while_waiting_for_room_creates_no_job(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    apiserver.pod_quota = 1
    apiserver.pods[(NAMESPACE, "someone-else")] = {
        "metadata": {"name": "someone-else", "namespace": NAMESPACE, "labels": {}},
        "status": {"phase": "Running"},
    }
    run = Run(api, wsettings, committed_sessions)
    until(lambda: waiting_for_room(committed_sessions, queued.id), "the claim waiting for room")
    detail = submission_of(committed_sessions, queued.id).progress["detail"]
    assert detail == "quota eval-quota: pods 1 used of 1, the Job needs 1"
    cancel_now(committed_sessions, queued.id)
    assert run.wait() == State.CANCELLED
    assert [r for r in apiserver.requests if r.method == "POST"] == []


def test_a_job_that_fits_the_quota_only_without_its_runtime_class_overhead_waits_for_room(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    """The quota counts the sandbox's overhead in every pod: a worker that left it out would
    create the Job, see its pod refused, take it back and make it again, round and round."""
    gvisor = {"cpu": "100m", "memory": "128Mi"}
    apiserver.runtime_classes["gvisor"] = gvisor
    sandboxed = k8s_worker(
        settings, apiserver, k8s_runtime_class="gvisor", k8s_runtime_overhead=gvisor
    )
    # Room for the Job's containers (2 CPUs of the evaluator, 1 of the policy) but not for
    # its overhead on top, beside someone else's pod of 1 CPU.
    apiserver.compute_quota = {"requests.cpu": "4050m"}
    other = (NAMESPACE, "someone-else")
    apiserver.pods[other] = {
        "metadata": {"name": other[1], "namespace": NAMESPACE, "labels": {}},
        "spec": {"containers": [{"name": "x", "resources": {"requests": {"cpu": "1"}}}]},
        "status": {"phase": "Running"},
    }
    apiserver.on_create = apiserver.run  # the controller makes the pods at once
    run = Run(api, sandboxed, committed_sessions)
    until(lambda: waiting_for_room(committed_sessions, queued.id), "the claim waiting for room")
    detail = submission_of(committed_sessions, queued.id).progress["detail"]
    assert detail.startswith("quota eval-quota: requests.cpu 1 used of 4.05, the Job needs 3.1")
    assert apiserver.created_bodies() == []  # no Job made only for its pod to be refused
    with apiserver.lock:
        del apiserver.pods[other]
    name = job_name(queued.id, 1)
    until(lambda: apiserver.pods_of(NAMESPACE, name), "the Job made, its pod admitted")
    assert apiserver.pods_of(NAMESPACE, name)[0]["spec"]["overhead"] == gvisor
    apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, queued.id)])
    assert run.wait() == State.SUCCEEDED
    assert apiserver.events == []  # no pod was ever refused


def test_a_cancel_stops_the_job_between_looks(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    """Nothing changes in the cluster and the watcher's own looks are minutes apart here, yet
    the cancel deletes the Job at once: it asks the server every second whether the attempt
    still runs."""
    slow = k8s_worker(settings, apiserver, k8s_poll_interval=300)
    name = job_name(queued.id, 1)
    run = start(api, slow, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name)
    cancel_now(committed_sessions, queued.id)
    assert run.wait() == State.CANCELLED  # joined within 120 s: long before the next look
    assert (name, "Foreground") in apiserver.deletions
    made = apiserver.counts()
    assert made["get pods/log"] == 0  # no progress read, no result read
    assert made["list pods"] == 1  # the watch's first list: no look at the pods of its own


def test_a_job_whose_pods_the_quota_refuses_is_made_again_with_a_new_deadline_when_there_is_room(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    """Another worker took the room between this worker's look at the quota and its Job's
    creation: rather than leave the Job's pods to the controller while its deadline runs, the
    worker takes the Job back and makes it again once there is room."""
    apiserver.pod_quota = 1
    name = job_name(queued.id, 1)
    created: list[str] = []
    other = (NAMESPACE, "someone-elses-pod")

    def controller(namespace: str, job: str) -> None:
        created.append(job)
        if len(created) == 1:  # the race: the room is gone by the time the pods are made
            apiserver.pods[other] = {
                "metadata": {"name": other[1], "namespace": namespace, "labels": {}},
                "status": {"phase": "Running"},
            }
        apiserver.run(namespace, job)

    apiserver.on_create = controller
    run = Run(api, wsettings, committed_sessions)
    until(
        lambda: len(created) == 1 and (NAMESPACE, name) not in apiserver.jobs, "the Job taken back"
    )
    until(
        lambda: (
            (submission_of(committed_sessions, queued.id).progress or {}).get("phase")
            == "waiting for room in the cluster"
        ),
        "the attempt waiting for room",
    )
    first_deadline = submission_of(committed_sessions, queued.id).deadline_at
    assert first_deadline is not None
    made_again_after = utcnow()
    with apiserver.lock:
        del apiserver.pods[other]  # the other evaluation ends
    until(lambda: len(created) == 2 and apiserver.pods_of(NAMESPACE, name), "the Job made again")
    # The new Job's deadline runs from its creation: the attempt's moves with it, else a long
    # wait for room would end in the reconciler's `timed_out`, charged to the participant.
    job_deadline = apiserver.jobs[(NAMESPACE, name)]["spec"]["activeDeadlineSeconds"]
    moved = made_again_after + timedelta(seconds=job_deadline + watch_module.JOB_DEADLINE_GRACE_S)
    until(
        lambda: submission_of(committed_sessions, queued.id).deadline_at >= moved,  # type: ignore[operator]
        "the new Job's deadline reported",
    )
    assert moved > first_deadline
    plan = plan_of(committed_sessions, settings, queued.id)
    document = build_result(plan, "image", [ShardOutcome()], started=STARTED)
    apiserver.succeed(NAMESPACE, name, [printed(document)])
    assert run.wait() == State.SUCCEEDED
    submission = submission_of(committed_sessions, queued.id)
    assert (submission.state, submission.attempt) == (State.SUCCEEDED, 1)  # not a re-run


def result_of(sessions: sessionmaker[Session], settings: Settings, sid: int) -> str:
    """A complete result document for the attempt, as its evaluator prints it."""
    plan = plan_of(sessions, settings, sid)
    return printed(build_result(plan, "image", [ShardOutcome()], started=STARTED))


def test_a_running_job_costs_no_request_between_changes_and_its_logs_are_read_at_the_end(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    quiet = k8s_worker(settings, apiserver, k8s_progress_interval=3600)
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, quiet, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    looked_twice(apiserver, quiet, committed_sessions, sid)
    before = len(apiserver.requests)
    for _ in range(3):  # seconds of a running Job: heartbeats to the server, none to the cluster
        looked_twice(apiserver, quiet, committed_sessions, sid)
    assert set(apiserver.counts(before)) <= {"watch jobs", "watch pods"}
    apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
    assert run.wait() == State.SUCCEEDED
    reads = [r for r in apiserver.requests if r.path.endswith("/log")]
    assert [r.query["container"] for r in reads] == [["evaluator"], ["policy"]]


def test_a_410_while_a_job_runs_lists_again_and_the_job_is_followed_to_its_end(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    looked_twice(apiserver, wsettings, committed_sessions, sid)
    lists = apiserver.counts()["list jobs"]
    with apiserver.together():  # the history is compacted past the watch, and the Job ends
        apiserver.expire_watches()
        apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
    assert run.wait() == State.SUCCEEDED
    assert apiserver.counts()["list jobs"] > lists  # listed again: the 410's remedy


def test_an_api_outage_shorter_than_the_workers_tolerance_does_not_end_the_attempt(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Once back, the API server says nothing for a minute (its first bookmark) or more: the
    watch opening again is what ends the outage, not the first event."""
    monkeypatch.setattr(watch_module, "API_OUTAGE_S", 10.0)  # ten minutes in production
    monkeypatch.setattr(informer_module, "RETRY", Backoff(attempts=1000, base_s=0.05, cap_s=0.2))
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    looked_twice(apiserver, wsettings, committed_sessions, sid)

    def phase() -> str | None:
        return (submission_of(committed_sessions, sid).progress or {}).get("phase")

    apiserver.fail_next("GET", "/jobs", *[503] * 1000)
    apiserver.cut_watches()  # the API server restarts, and refuses requests for a while
    until(lambda: phase() == "unknown", "the worker to report the outage")
    apiserver.clear_faults()  # back, within the worker's tolerance
    until(
        lambda: phase() == "running" or not run.thread.is_alive(),
        "the worker to follow the Job again",
    )
    assert run.submission(sid).state == State.RUNNING
    apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
    assert run.wait() == State.SUCCEEDED


def test_a_restarted_worker_adopts_the_running_job_and_follows_it_to_its_end(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    sid, name = queued.id, job_name(queued.id, 1)
    a_worker_dies(api, wsettings, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    apiserver.write_log(NAMESPACE, name, "evaluator", "manieval: run 0 episode 0: success\n")
    lists = apiserver.counts()["list jobs"]

    outcome: list[State | None] = []
    second = threading.Thread(target=lambda: outcome.append(resume_watch(api, wsettings, sid, 1)))
    second.start()
    until(
        lambda: (submission_of(committed_sessions, sid).progress or {}).get("done") == 1, "progress"
    )
    assert apiserver.counts()["list jobs"] == lists + 1  # the new watch's own first list
    apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
    second.join(timeout=60)
    assert outcome == [State.SUCCEEDED]
    assert [d for d in apiserver.deletions if d[0] == name] == [(name, "Foreground")]


def test_an_image_pull_the_kubelet_retries_is_waited_for_until_it_succeeds(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    """A registry restarting (the one-replica registry in a rollout): the kubelet tries the
    pull again after a back-off, and the evaluation runs once it succeeds."""
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name, ready=False)
    for reason in ("ErrImagePull", "ImagePullBackOff", "ErrImagePull", "ImagePullBackOff"):
        apiserver.cannot_pull(NAMESPACE, name, "policy", reason=reason)
        looked_twice(apiserver, wsettings, committed_sessions, sid)
        assert run.submission(sid).state == State.RUNNING, reason
    apiserver.pulled(NAMESPACE, name)
    apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
    assert run.wait() == State.SUCCEEDED


def test_a_participants_image_that_never_pulls_is_an_error_after_the_pending_timeout(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    """Their pushed image, pinned by digest, that the kubelet cannot pull: `error` as the
    docker executor's failed pull (no quota used), not run again (it would not pull then)."""

    def kubelet(namespace: str, name: str) -> None:
        apiserver.run(namespace, name, ready=False)
        apiserver.cannot_pull(namespace, name, "policy")

    apiserver.on_create = kubelet
    patient = k8s_worker(settings, apiserver, k8s_pending_timeout_s=0.5)
    assert Run(api, patient, committed_sessions).wait() == State.ERROR
    end = attempt_end(committed_sessions, queued.id)
    assert end.cause is None
    prefix = "the evaluation could not start: the policy container: ImagePullBackOff: Back-off"
    assert end.reason.startswith(prefix), end.reason
    assert submission_of(committed_sessions, queued.id).attempt == 1


def test_the_platforms_evaluator_image_that_never_pulls_is_the_clusters_doing(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
) -> None:
    def kubelet(namespace: str, name: str) -> None:
        apiserver.run(namespace, name, ready=False)
        apiserver.cannot_pull(namespace, name, "evaluator", reason="ErrImagePull")

    apiserver.on_create = kubelet
    patient = k8s_worker(settings, apiserver, k8s_pending_timeout_s=0.5)
    reason = assert_cluster_error(
        committed_sessions, queued.id, Run(api, patient, committed_sessions).wait()
    )
    assert reason.startswith("the cluster stopped the evaluation: an image could not be pulled")
    assert "the evaluator container: ErrImagePull: failed to pull and unpack image" in reason


@pytest.mark.parametrize(
    ("reason", "message", "job_fails"),
    [
        ("OutOfcpu", "Node didn't have enough resource: cpu", True),
        ("OutOfmemory", "Node didn't have enough resource: memory", False),
        (
            "UnexpectedAdmissionError",
            "Allocate failed due to no healthy devices present; cannot allocate unhealthy "
            "devices nvidia.com/gpu, which is unexpected",
            True,
        ),
    ],
    ids=["out-of-cpu", "out-of-memory-job-not-yet-failed", "device-plugin"],
)
def test_a_pod_its_nodes_kubelet_refuses_is_the_clusters_doing(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    queued: Submission,
    reason: str,
    message: str,
    job_fails: bool,
) -> None:
    name = job_name(queued.id, 1)
    run = start(api, wsettings, committed_sessions, apiserver, queued.id)
    apiserver.run(NAMESPACE, name, ready=False)  # scheduled; the kubelet has not admitted it
    apiserver.refuse(NAMESPACE, name, reason=reason, message=message, job_fails=job_fails)
    said = assert_cluster_error(committed_sessions, queued.id, run.wait())
    assert f"was refused by its node's kubelet ({reason}: {message}" in said, said


@pytest.mark.parametrize(
    "lose",
    [
        lambda api, name: api.collect_pods(NAMESPACE, name),
        lambda api, name: api.lose_kubelet(NAMESPACE, name),
        lambda api, name: api.fail_next("GET", "/log", 404),
    ],
    ids=["pod-collected", "node-unreachable", "log-404"],
)
def test_a_result_log_lost_with_its_pod_or_node_is_the_clusters_doing(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
    queued: Submission,
    lose: Callable[[ApiServerDouble, str], object],
) -> None:
    quiet = k8s_worker(settings, apiserver, k8s_progress_interval=3600)  # no log read before
    sid, name = queued.id, job_name(queued.id, 1)
    run = start(api, quiet, committed_sessions, apiserver, sid)
    apiserver.run(NAMESPACE, name)
    looked_twice(apiserver, quiet, committed_sessions, sid)
    with apiserver.together():  # the Job ends, and its pod or node goes before the worker looks
        apiserver.succeed(NAMESPACE, name, [result_of(committed_sessions, settings, sid)])
        lose(apiserver, name)
    reason = assert_cluster_error(committed_sessions, sid, run.wait())
    assert reason.startswith("the evaluation's log was lost: "), reason
