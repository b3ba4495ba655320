"""The Job lifecycle through the official client, against the API-server double over HTTP."""

from __future__ import annotations

import base64
import io
import json
from collections.abc import Callable, Iterator
from datetime import UTC, datetime

import pytest

from evaluator.evaluation import build_result
from evaluator.job import ShardReport, result_from_logs, write_document
from evaluator.plan import EvaluationPlan
from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.runner import ShardOutcome
from server.kit.settings import Settings
from testkit.k8s_double import (
    CONTROLLERS,
    NAMESPACE,
    ApiServerDouble,
    collect_logs,
    executor_for,
    running_apiserver,
)
from testkit.workers import worker_settings
from tests.worker.k8s_specs import (
    make_spec,
)
from worker.kubernetes.client import (
    Backoff,
    JobConflict,
    KubernetesError,
    KubernetesExecutor,
    LogLost,
    StartedJob,
    kubernetes_executor,
)
from worker.kubernetes.manifest import build_job, job_labels
from worker.kubernetes.status import JobStatus, PodView

STARTED = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)


@pytest.fixture(params=CONTROLLERS)
def apiserver(request: pytest.FixtureRequest) -> Iterator[ApiServerDouble]:
    """The double, its Job controller ending Jobs in the order of each version (1.29, 1.31+)."""
    with running_apiserver(request.param) as double:
        yield double


def episode(index: int, seed: int, *, success: bool = True) -> EpisodeResult:
    return EpisodeResult(
        index=index,
        seed=seed,
        success_once=success,
        success_at_end=success,
        steps=5,
        episode_return=1.5,
        wall_time_s=0.1,
    )


def plan_of(spec_shards: int = 1) -> EvaluationPlan:
    return make_spec(shards=spec_shards).evaluation.plan()


def result_log(plan: EvaluationPlan) -> tuple[EvaluationResult, str]:
    """A pod's evaluator log: noise around the printed result document."""
    episodes = [(0, episode(i, seed)) for i, seed in enumerate(plan.runs[0].seeds)]
    result = build_result(plan, "image", [ShardOutcome(episodes=episodes)], started=STARTED)
    out = io.StringIO()
    out.write("manieval: run 0 episode 0: success\nsapien: warning\n")
    write_document(result, out)
    out.write("exiting\n")
    return result, out.getvalue()


def shard_log(plan: EvaluationPlan, index: int, shards: int) -> str:
    run = plan.runs[0]
    mine = [(0, episode(i, s)) for i, s in enumerate(run.seeds) if i % shards == index]
    report = ShardReport(
        index=index,
        shards=shards,
        policy="image",
        versions=build_result(plan, "x", [], started=STARTED).versions,
        started_at=STARTED,
        finished_at=STARTED,
        episodes=mine,
    )
    out = io.StringIO()
    write_document(report, out)
    return out.getvalue()


def test_a_job_is_created_from_the_manifest_and_runs_to_success(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    spec = make_spec()
    assert executor.start(spec) == StartedJob("eval-7-1", adopted=False)
    assert apiserver.created_bodies() == [build_job(spec)]
    assert executor.status(7, 1) == JobStatus("pending")
    apiserver.run(NAMESPACE, "eval-7-1")
    assert executor.status(7, 1) == JobStatus("running")
    result, log = result_log(plan_of())
    apiserver.succeed(NAMESPACE, "eval-7-1", [log])
    assert executor.status(7, 1) == JobStatus("succeeded")
    logs = collect_logs(executor, 7, 1)
    assert logs == [log]
    assert result_from_logs(plan_of(), logs) == result


def test_a_started_but_unscheduled_pod_keeps_the_job_pending(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.run(NAMESPACE, "eval-7-1", ready=False)
    assert executor.status(7, 1) == JobStatus("pending")
    assert collect_logs(executor, 7, 1) == [""]  # the evaluator has not started: no log yet


def test_an_indexed_job_gives_one_log_per_shard_and_they_merge(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    spec = make_spec(shards=2)
    executor.start(spec)
    assert len(apiserver.run(NAMESPACE, "eval-7-1")) == 2
    plan = spec.evaluation.plan()
    logs = [shard_log(plan, 0, 2), shard_log(plan, 1, 2)]
    apiserver.succeed(NAMESPACE, "eval-7-1", logs)
    collected = collect_logs(executor, 7, 1)
    assert collected == logs
    merged = result_from_logs(plan, collected)
    assert [e.seed for e in merged.conditions[0].tasks[0].episodes] == [100, 101]
    assert merged.status == "completed"


def test_the_policy_log_tail_can_be_collected_too(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    policy_log = "".join(f"line {i}\n" for i in range(10))
    apiserver.succeed(NAMESPACE, "eval-7-1", ["x"], policy_logs=[policy_log])
    assert collect_logs(executor, 7, 1, container="policy", tail_lines=2) == ["line 8\nline 9\n"]


@pytest.mark.parametrize("reason", ["EvictionByEvictionAPI", "PreemptionByScheduler"])
def test_a_disruption_fails_the_job_by_its_pod_failure_policy_and_makes_no_new_pod(
    apiserver: ApiServerDouble, reason: str
):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    [pod] = apiserver.run(NAMESPACE, "eval-7-1")
    assert apiserver.evict(NAMESPACE, "eval-7-1", reason=reason) is None  # no replacement
    rule = f"Pod {NAMESPACE}/{pod} has condition DisruptionTarget matching FailJob rule at index 0"
    conditions = apiserver.jobs[(NAMESPACE, "eval-7-1")]["status"]["conditions"]
    interim = ["FailureTarget"] if apiserver.controller == "1.31" else ["FailureTarget", "Failed"]
    assert [c["type"] for c in conditions] == interim
    assert {(c["reason"], c["message"]) for c in conditions} == {("PodFailurePolicy", rule)}
    assert apiserver.pods_of(NAMESPACE, "eval-7-1") == []  # deleted once counted
    status = executor.status(7, 1)
    assert (status.phase, status.reason) == ("failed", f"PodFailurePolicy: {rule}")
    said = (
        f"pod {pod} was disrupted by the cluster, which failed its Job (PodFailurePolicy: {rule})"
    )
    assert status.disrupted == said  # from the Job alone: its pod is gone
    assert executor.pods(7, 1).disrupted == said
    apiserver.settle(NAMESPACE, "eval-7-1")
    assert executor.status(7, 1).disrupted == said


def test_a_sharded_jobs_disrupted_pods_stay_listed_and_say_why(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec(shards=2))
    first, second = apiserver.run(NAMESPACE, "eval-7-1")
    apiserver.disrupt(NAMESPACE, "eval-7-1")  # both evicted, still listed
    listed = {p["metadata"]["name"]: p for p in apiserver.pods_of(NAMESPACE, "eval-7-1")}
    assert set(listed) == {first, second}
    assert {p["status"]["phase"] for p in listed.values()} == {"Failed"}
    assert "(EvictionByEvictionAPI" in str(executor.pods(7, 1).disrupted)
    assert executor.status(7, 1).phase == "failed"


def test_under_an_ignore_rule_the_double_replaces_a_disrupted_pod(apiserver: ApiServerDouble):
    manifest = build_job(make_spec())
    manifest["spec"]["podFailurePolicy"]["rules"][0]["action"] = "Ignore"
    apiserver.put_job(manifest)
    executor = executor_for(apiserver)
    [first] = apiserver.run(NAMESPACE, "eval-7-1")
    apiserver.logs[(NAMESPACE, first, "evaluator")] = "evicted half way"
    replacement = apiserver.disrupt(NAMESPACE, "eval-7-1")
    assert replacement is not None
    assert executor.status(7, 1).phase != "failed"
    apiserver.succeed(NAMESPACE, "eval-7-1", ["the rerun's log"])
    assert collect_logs(executor, 7, 1) == ["the rerun's log"]


@pytest.mark.parametrize("reason", ["PodFailurePolicy", "BackoffLimitExceeded"])
def test_a_failed_job_reports_the_controllers_reason(apiserver: ApiServerDouble, reason: str):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.run(NAMESPACE, "eval-7-1")
    apiserver.fail(NAMESPACE, "eval-7-1", reason=reason, message="evaluator exit code 1")
    status = executor.status(7, 1)
    assert status.phase == "failed"
    assert status.reason == f"{reason}: evaluator exit code 1"
    assert status.disrupted is None  # the evaluator's failure, not a disruption


def test_a_failed_jobs_evaluator_log_is_still_readable(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.run(NAMESPACE, "eval-7-1")
    apiserver.fail(NAMESPACE, "eval-7-1", logs=["Traceback (most recent call last): ..."])
    assert collect_logs(executor, 7, 1) == ["Traceback (most recent call last): ..."]


def test_a_job_past_its_deadline_is_deadline_exceeded(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.run(NAMESPACE, "eval-7-1")
    apiserver.exceed_deadline(NAMESPACE, "eval-7-1")
    status = executor.status(7, 1)
    assert status.phase == "deadline_exceeded"
    assert "DeadlineExceeded" in status.reason
    assert collect_logs(executor, 7, 1) == [""]  # the controller deleted the running pod


def test_the_jobs_deadline_counts_from_its_creation_on_the_clusters_clock(
    apiserver: ApiServerDouble,
):
    """The controller sets startTime at its first sync, before any pod is scheduled or
    pulled, and fails the Job once the clock passes startTime + activeDeadlineSeconds (900 s
    here), whatever the pods are doing; 1.31 writes FailureTarget first, 1.29 Failed."""
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.advance(600)  # scheduling and pulls take their time...
    apiserver.run(NAMESPACE, "eval-7-1")
    apiserver.advance(250)
    assert executor.status(7, 1) == JobStatus("running")
    apiserver.advance(60)  # ...and count against the deadline
    status = executor.status(7, 1)
    assert (status.phase, status.reason) == (
        "deadline_exceeded",
        "DeadlineExceeded: Job was active longer than specified deadline",
    )
    job = apiserver.jobs[(NAMESPACE, "eval-7-1")]
    conditions = [c["type"] for c in job["status"]["conditions"]]
    assert conditions == (["FailureTarget"] if apiserver.controller == "1.31" else ["Failed"])
    apiserver.advance(3600)  # a Job already failed is not failed again
    assert [c["type"] for c in job["status"]["conditions"]] == conditions


def test_a_job_that_does_not_exist_is_missing(apiserver: ApiServerDouble):
    assert executor_for(apiserver).status(99, 1) == JobStatus("missing", "no Job eval-99-1")


def test_an_existing_job_of_the_same_attempt_is_adopted_on_409(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    spec = make_spec()
    apiserver.put_job(build_job(spec))
    assert executor.start(spec) == StartedJob("eval-7-1", adopted=True)
    assert len(apiserver.jobs) == 1


def test_a_lost_create_response_is_retried_and_the_created_job_adopted(
    apiserver: ApiServerDouble,
):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps)
    apiserver.fail_next("POST", "/jobs", 500, apply=True)  # created, but the answer is a 500
    assert executor.start(make_spec()) == StartedJob("eval-7-1", adopted=True)
    assert len(apiserver.jobs) == 1
    assert len(sleeps) == 1


def test_a_409_for_a_job_of_another_attempt_is_a_conflict(apiserver: ApiServerDouble):
    foreign = build_job(make_spec(submission_id=7, attempt=1))
    foreign["metadata"]["labels"] = job_labels(8, 1)
    apiserver.put_job(foreign)
    with pytest.raises(JobConflict, match="other labels"):
        executor_for(apiserver).start(make_spec())


def test_a_409_for_a_job_being_deleted_is_a_conflict_not_an_adoption(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    apiserver.hold_deletions = True
    executor.start(make_spec())
    assert executor.cancel(7, 1)
    with pytest.raises(JobConflict, match="being deleted"):
        executor.start(make_spec())
    apiserver.finish_deletions()
    assert executor.start(make_spec()).adopted is False


def test_429_and_5xx_are_retried_with_backoff_then_succeed(apiserver: ApiServerDouble):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps)
    apiserver.fail_next("POST", "/jobs", 500, 503)
    apiserver.fail_next("POST", "/jobs", 429, retry_after=3)
    assert executor.start(make_spec()) == StartedJob("eval-7-1", adopted=False)
    # base 0.5 s doubling, times the (fixed) jitter 0.5; a Retry-After is honoured
    assert sleeps == [0.25, 0.5, 3.0]
    assert len(apiserver.created_bodies()) == 4


def test_reads_and_deletes_are_retried_too(apiserver: ApiServerDouble):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps)
    executor.start(make_spec())
    apiserver.fail_next("GET", "/jobs/eval-7-1", 502)
    apiserver.fail_next("DELETE", "/jobs/eval-7-1", 504)
    assert executor.status(7, 1).phase == "pending"
    assert executor.cancel(7, 1)
    assert len(sleeps) == 2


def test_retries_stop_after_the_last_attempt(apiserver: ApiServerDouble):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps, attempts=3)
    apiserver.fail_next("POST", "/jobs", 500, 500, 500, 500)
    with pytest.raises(KubernetesError) as caught:
        executor.start(make_spec())
    assert caught.value.status == 500
    assert len(apiserver.created_bodies()) == 3
    assert len(sleeps) == 2


@pytest.mark.parametrize("status", [400, 401, 403, 422])
def test_client_errors_are_not_retried(apiserver: ApiServerDouble, status: int):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps)
    apiserver.fail_next("POST", "/jobs", status)
    with pytest.raises(KubernetesError) as caught:
        executor.start(make_spec())
    assert caught.value.status == status
    assert sleeps == []
    assert len(apiserver.requests) == 1


def test_backoff_grows_exponentially_up_to_its_cap_with_full_jitter():
    backoff = Backoff(attempts=20, base_s=0.5, cap_s=8.0)
    ceilings = [backoff.delay(retry, 0.999999, None) for retry in range(10)]
    assert ceilings == sorted(ceilings)
    assert max(ceilings) < 8.0
    assert ceilings[0] == pytest.approx(0.5, rel=1e-5)
    assert backoff.delay(3, 0.0, None) == 0.0  # full jitter: anything from zero
    assert backoff.delay(0, 0.1, 60.0) == 8.0  # a Retry-After beyond the cap is capped


def test_cancel_deletes_in_the_foreground_and_takes_the_pods(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.run(NAMESPACE, "eval-7-1")
    assert executor.cancel(7, 1) is True
    assert apiserver.deletions == [("eval-7-1", "Foreground")]
    assert apiserver.pods_of(NAMESPACE, "eval-7-1") == []
    assert executor.status(7, 1).phase == "missing"


def test_cancelling_a_job_that_is_gone_is_not_an_error(apiserver: ApiServerDouble):
    assert executor_for(apiserver).cancel(7, 1) is False


def test_orphan_cleanup_deletes_only_our_jobs_of_inactive_attempts(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    for submission, attempt in [(7, 1), (8, 1), (9, 2), (7, 2)]:
        executor.start(make_spec(submission_id=submission, attempt=attempt))
    stranger = build_job(make_spec(submission_id=5))
    stranger["metadata"] |= {"name": "someone-elses", "labels": {"app": "other"}}
    apiserver.put_job(stranger)
    deleted = executor.delete_orphans(keep={(7, 2), (9, 1)})
    assert sorted(deleted) == ["eval-7-1", "eval-8-1", "eval-9-2"]
    assert sorted(name for _, name in apiserver.jobs) == ["eval-7-2", "someone-elses"]
    assert {policy for _, policy in apiserver.deletions} == {"Foreground"}


def test_list_jobs_follows_pagination_and_reports_each_attempt(apiserver: ApiServerDouble):
    for submission in range(1, 202):  # one more than a page
        apiserver.put_job(build_job(make_spec(submission_id=submission)))
    apiserver.run(NAMESPACE, "eval-3-1")
    refs = executor_for(apiserver).list_jobs()
    assert sorted(r.submission_id for r in refs) == list(range(1, 202))
    assert next(r for r in refs if r.submission_id == 3).status == JobStatus("running")
    lists = [r for r in apiserver.requests if r.method == "GET" and r.path.endswith("/jobs")]
    assert len(lists) == 2


def test_the_clients_own_retries_are_off_the_backoff_is_the_only_one(
    settings: Settings, apiserver: ApiServerDouble
):
    wsettings = worker_settings(settings, k8s_api_url=apiserver.host, k8s_namespace=NAMESPACE)
    executor = kubernetes_executor(wsettings)
    sleeps: list[float] = []
    executor.sleep = sleeps.append
    try:
        apiserver.fail_next("GET", "/jobs/eval-7-1", 503, retry_after=0)
        apiserver.fail_next("GET", "/jobs/eval-7-1", 429, retry_after=0)
        assert executor.status(7, 1).phase == "missing"
    finally:
        executor.close()
    # urllib3 retries answers with a Retry-After itself, unseen, unless it is told not to
    assert len(sleeps) == 2
    reads = [r for r in apiserver.requests if r.path.endswith("/jobs/eval-7-1")]
    assert len(reads) == 3


def test_an_unreachable_api_server_is_retried_with_backoff_only(apiserver: ApiServerDouble):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps, attempts=3)
    executor.api.configuration.host = "http://127.0.0.1:1"  # nothing listens there
    with pytest.raises(KubernetesError, match="cannot be reached"):
        executor.status(7, 1)
    assert sleeps == [0.25, 0.5]


def test_an_expired_continue_token_lists_again_from_the_start(apiserver: ApiServerDouble):
    for submission in range(1, 202):
        apiserver.put_job(build_job(make_spec(submission_id=submission)))
    apiserver.expire_continue = True  # 410 Gone for the second page
    refs = executor_for(apiserver).list_jobs()
    assert sorted(r.submission_id for r in refs) == list(range(1, 202))  # no page twice
    lists = [r for r in apiserver.requests if r.method == "GET" and r.path.endswith("/jobs")]
    assert len(lists) == 4  # page 1, page 2 (410), page 1 again, page 2


def test_a_job_beyond_the_quota_is_refused_with_the_clusters_reason(apiserver: ApiServerDouble):
    apiserver.job_quota = 1
    executor = executor_for(apiserver)
    executor.start(make_spec(submission_id=1))
    with pytest.raises(KubernetesError, match="exceeded quota") as caught:
        executor.start(make_spec(submission_id=2))
    assert caught.value.status == 403
    assert len(apiserver.created_bodies()) == 2  # a refusal is not retried


def test_the_pods_say_what_the_cluster_did_to_them(apiserver: ApiServerDouble):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    assert executor.pods(7, 1) == PodView()
    (pod,) = apiserver.unschedulable(NAMESPACE, "eval-7-1")
    view = executor.pods(7, 1)
    assert view.unschedulable == "0/3 nodes are available: 3 Insufficient nvidia.com/gpu."
    assert (view.alive, view.names, view.disrupted) == ({pod}, {pod}, None)
    apiserver.lose_node(NAMESPACE, "eval-7-1")
    assert "(DeletionByTaintManager: Taint manager" in str(executor.pods(7, 1).disrupted)
    apiserver.evict(NAMESPACE, "eval-7-1")  # deleted: only the failed Job says it now
    view = executor.pods(7, 1)
    assert view.names == set()
    assert f"pod {pod} was disrupted by the cluster, which failed its Job" in str(view.disrupted)


def test_the_quotas_refusal_of_a_pod_is_in_the_jobs_events(apiserver: ApiServerDouble):
    apiserver.pod_quota = 0
    executor = executor_for(apiserver)
    executor.start(make_spec())
    executor.start(make_spec(submission_id=8))
    assert executor.events(7, 1) == []
    assert apiserver.run(NAMESPACE, "eval-7-1") == []
    apiserver.run(NAMESPACE, "eval-8-1")
    (warning,) = executor.events(7, 1)  # only this Job's
    assert warning.startswith('FailedCreate: Error creating: pods "eval-7-1-')
    assert "exceeded quota: eval-quota" in warning
    assert executor.pods(7, 1).count == 0


def test_the_evaluation_travels_in_a_secret_the_job_owns_and_takes_along(
    apiserver: ApiServerDouble,
):
    executor = executor_for(apiserver)
    spec = make_spec()
    executor.start(spec)
    job = apiserver.jobs[(NAMESPACE, "eval-7-1")]
    secret = apiserver.secrets[(NAMESPACE, "eval-7-1-evaluation")]
    owner = {"apiVersion": "batch/v1", "kind": "Job", "name": "eval-7-1"}
    assert secret["metadata"]["ownerReferences"] == [
        owner | {"uid": job["metadata"]["uid"], "blockOwnerDeletion": True}
    ]
    document = base64.b64decode(secret["data"]["evaluation.json"]).decode()
    assert document == spec.evaluation.canonical_json()
    assert document not in json.dumps(job)
    posts = [r.path for r in apiserver.requests if r.method == "POST"]
    assert posts == [
        f"/apis/batch/v1/namespaces/{NAMESPACE}/jobs",
        f"/api/v1/namespaces/{NAMESPACE}/secrets",
    ]
    assert executor.cancel(7, 1)
    assert apiserver.secrets == {}  # the garbage collector took it with its owner


def test_an_adopted_job_gets_its_secret_if_its_creator_died_before_making_it(
    apiserver: ApiServerDouble,
):
    executor = executor_for(apiserver)
    apiserver.put_job(build_job(make_spec()))  # created, then the worker died
    assert executor.start(make_spec()).adopted is True
    secret = apiserver.secrets[(NAMESPACE, "eval-7-1-evaluation")]
    uid = apiserver.jobs[(NAMESPACE, "eval-7-1")]["metadata"]["uid"]
    assert secret["metadata"]["ownerReferences"][0]["uid"] == uid
    assert executor.start(make_spec()).adopted is True  # and again: the Secret exists (409)
    assert len(apiserver.secrets) == 1


def test_a_job_made_again_after_its_deletion_never_adopts_its_predecessors_secret(
    apiserver: ApiServerDouble,
):
    """The Secret blocks its Job's foreground deletion (blockOwnerDeletion): however far
    behind the garbage collector is, the old Job stays until its Secret is gone, so the Job
    made again meets no Secret to adopt and then lose under its pod."""
    executor = executor_for(apiserver)
    apiserver.gc_paused = True  # the collector is behind: the test makes its passes
    executor.start(make_spec())
    assert executor.cancel(7, 1)
    with pytest.raises(JobConflict, match="being deleted"):
        executor.start(make_spec())  # the collector has not ended the deletion yet
    apiserver.collect_garbage()  # it does: the Secret first, then the Job
    again = executor.start(make_spec())
    assert not again.adopted
    apiserver.collect_garbage()  # its next pass: what the old Job left is gone, not the new's
    secret = apiserver.secrets.get((NAMESPACE, "eval-7-1-evaluation"))
    assert secret is not None, "the new Job's Secret was collected with the old Job"
    assert secret["metadata"]["ownerReferences"][0]["uid"] == again.uid


def delete_in_background(executor: KubernetesExecutor, name: str) -> None:
    """As `kubectl delete job` does: the Job goes at once, its dependents later."""
    executor.batch.delete_namespaced_job(name, NAMESPACE, propagation_policy="Background")


def test_a_secret_a_background_deletion_left_is_waited_for_then_the_new_jobs_own_is_made(
    apiserver: ApiServerDouble,
):
    executor = executor_for(apiserver)
    apiserver.gc_paused = True
    executor.start(make_spec())
    delete_in_background(executor, "eval-7-1")
    waits: list[float] = []

    def collector_catches_up(seconds: float) -> None:
        waits.append(seconds)
        apiserver.collect_garbage()

    executor.sleep = collector_catches_up
    again = executor.start(make_spec())
    assert waits == [0.25]  # one back-off, then the stale Secret was gone
    secret = apiserver.secrets[(NAMESPACE, "eval-7-1-evaluation")]
    assert secret["metadata"]["ownerReferences"][0]["uid"] == again.uid


def test_a_secret_a_background_deletion_left_for_too_long_is_an_error_not_adopted(
    apiserver: ApiServerDouble,
):
    sleeps: list[float] = []
    executor = executor_for(apiserver, sleeps=sleeps)
    apiserver.gc_paused = True  # and stays behind
    executor.start(make_spec())
    delete_in_background(executor, "eval-7-1")
    with pytest.raises(KubernetesError, match="of a deleted Job eval-7-1 is still there") as exc:
        executor.start(make_spec())
    assert exc.value.status == 409
    assert not isinstance(exc.value, JobConflict)  # the worker charges the cluster, runs again
    assert len(sleeps) == 5  # waited with back-off first


@pytest.mark.parametrize(
    ("lose", "said"),
    [
        (lambda api, name: api.collect_pods(NAMESPACE, name), "no pod of shard 0 is left"),
        (lambda api, name: api.lose_kubelet(NAMESPACE, name), "500 Internal Server Error"),
        (lambda api, name: api.fail_next("GET", "/log", 404), "404 Not Found"),
    ],
    ids=["pod-collected", "node-unreachable", "log-404"],
)
def test_a_result_log_lost_with_its_pod_or_node_is_told_apart(
    apiserver: ApiServerDouble, lose: Callable[[ApiServerDouble, str], object], said: str
):
    executor = executor_for(apiserver)
    executor.start(make_spec())
    apiserver.succeed(NAMESPACE, "eval-7-1", ["done"])
    lose(apiserver, "eval-7-1")
    with pytest.raises(LogLost, match=said):
        executor.result_logs(7, 1, 1)
