"""Watches: the API-server double serves them as a real server does, and the worker's
`ClusterWatch` follows Jobs and pods through them (lists once, resumes, re-lists on 410)."""

from __future__ import annotations

import copy
import json
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from typing import Any

import pytest

from testkit.k8s_double import (
    NAMESPACE,
    ApiServerDouble,
    collect_logs,
    executor_for,
    running_apiserver,
)
from testkit.waiting import until
from tests.worker.k8s_specs import (
    make_spec,
)
from worker.kubernetes.informer import ClusterWatch, Failure
from worker.kubernetes.manifest import build_job
from worker.kubernetes.status import job_status

JOBS = f"/apis/batch/v1/namespaces/{NAMESPACE}/jobs"
PODS = f"/api/v1/namespaces/{NAMESPACE}/pods"
OURS = "labelSelector=app.kubernetes.io/name%3Dmanieval"


@pytest.fixture
def apiserver() -> Iterator[ApiServerDouble]:
    with running_apiserver() as double:
        yield double


@pytest.fixture
def cluster(apiserver: ApiServerDouble) -> Iterator[ClusterWatch]:
    watch = ClusterWatch(executor_for(apiserver), watch_timeout_s=(2.0, 2.0))
    watch.start()
    yield watch
    watch.close()


def get(apiserver: ApiServerDouble, path: str) -> Any:
    with urllib.request.urlopen(apiserver.host + path, timeout=30) as answer:
        return json.load(answer)


def watch_lines(apiserver: ApiServerDouble, path: str) -> list[dict[str, Any]]:
    """Every event of a watch request, read until the server ends it."""
    with urllib.request.urlopen(apiserver.host + path, timeout=30) as answer:
        assert answer.headers["Transfer-Encoding"] == "chunked"
        return [json.loads(line) for line in answer.read().splitlines() if line.strip()]


def start_job(apiserver: ApiServerDouble, submission_id: int = 7) -> str:
    spec = make_spec(submission_id=submission_id)
    apiserver.put_job(build_job(spec))
    return spec.name


def test_a_watch_from_a_lists_version_streams_every_change_then_ends_at_its_timeout(
    apiserver: ApiServerDouble,
):
    name = start_job(apiserver)
    listed = get(apiserver, f"{JOBS}?{OURS}")
    version = listed["metadata"]["resourceVersion"]
    assert [j["metadata"]["resourceVersion"] for j in listed["items"]] == [version]
    apiserver.run(NAMESPACE, name)
    apiserver.succeed(NAMESPACE, name, ["done"])  # SuccessCriteriaMet (1.31)...
    apiserver.settle(NAMESPACE, name)  # ...then Complete
    apiserver.jobs.pop((NAMESPACE, name))  # a direct edit is published too
    events = watch_lines(
        apiserver, f"{JOBS}?watch=true&{OURS}&resourceVersion={version}&timeoutSeconds=1"
    )
    assert [e["type"] for e in events] == ["MODIFIED", "MODIFIED", "MODIFIED", "DELETED"]
    versions = [int(e["object"]["metadata"]["resourceVersion"]) for e in events]
    assert versions == sorted(versions)
    assert versions[0] > int(version)
    assert events[2]["object"]["status"]["conditions"][-1]["type"] == "Complete"


def test_a_watch_without_a_version_starts_with_the_current_objects_of_its_selector(
    apiserver: ApiServerDouble,
):
    name = start_job(apiserver)
    apiserver.run(NAMESPACE, name)
    apiserver.pods[(NAMESPACE, "someone-else")] = {
        "metadata": {"name": "someone-else", "namespace": NAMESPACE, "labels": {}},
        "status": {"phase": "Running"},
    }
    events = watch_lines(apiserver, f"{PODS}?watch=1&{OURS}&timeoutSeconds=1")
    assert [(e["type"], e["object"]["metadata"]["labels"]["job-name"]) for e in events] == [
        ("ADDED", name)
    ]


def test_bookmarks_come_only_when_asked_for_and_carry_the_version(apiserver: ApiServerDouble):
    version = get(apiserver, JOBS)["metadata"]["resourceVersion"]
    with urllib.request.urlopen(
        apiserver.host + f"{JOBS}?watch=true&resourceVersion={version}&timeoutSeconds=1", timeout=30
    ) as plain:
        apiserver.advance(3600)
        assert plain.read().splitlines() == []
    version = get(apiserver, JOBS)["metadata"]["resourceVersion"]
    with urllib.request.urlopen(
        apiserver.host
        + f"{JOBS}?watch=true&resourceVersion={version}&allowWatchBookmarks=true&timeoutSeconds=30",
        timeout=30,
    ) as marked:
        apiserver.advance(60)
        assert json.loads(marked.readline()) == {
            "type": "BOOKMARK",
            "object": {
                "kind": "Job",
                "apiVersion": "batch/v1",
                "metadata": {"resourceVersion": version},
            },
        }


def test_bookmarks_come_once_a_minute_of_the_clusters_clock_as_the_watch_cache_sends_them(
    apiserver: ApiServerDouble,
):
    version = get(apiserver, JOBS)["metadata"]["resourceVersion"]
    query = f"watch=true&resourceVersion={version}&allowWatchBookmarks=true&timeoutSeconds=30"
    with urllib.request.urlopen(f"{apiserver.host}{JOBS}?{query}", timeout=30) as stream:
        apiserver.advance(30)  # half a minute, nothing to say: no bookmark...
        name = start_job(apiserver)  # (its creation takes the cluster a second)
        added = json.loads(stream.readline())
        assert (added["type"], added["object"]["metadata"]["name"]) == ("ADDED", name)
        apiserver.advance(29)  # ...a minute after the watch began, one
        bookmark = json.loads(stream.readline())
        assert bookmark["type"] == "BOOKMARK"
        version = added["object"]["metadata"]["resourceVersion"]
        assert bookmark["object"]["metadata"] == {"resourceVersion": version}


def test_a_version_older_than_the_history_is_gone_in_the_stream(apiserver: ApiServerDouble):
    start_job(apiserver)
    version = get(apiserver, JOBS)["metadata"]["resourceVersion"]
    apiserver.expire_watches()
    (event,) = watch_lines(apiserver, f"{JOBS}?watch=true&resourceVersion={version}")
    assert event["type"] == "ERROR"
    assert (event["object"]["kind"], event["object"]["code"]) == ("Status", 410)
    fresh = get(apiserver, JOBS)["metadata"]["resourceVersion"]
    assert (
        watch_lines(apiserver, f"{JOBS}?watch=true&resourceVersion={fresh}&timeoutSeconds=1") == []
    )


def test_an_injected_410_answers_the_watch_request_itself(apiserver: ApiServerDouble):
    apiserver.fail_next("GET", "/jobs", 410)
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(apiserver.host + f"{JOBS}?watch=true", timeout=30)
    assert refused.value.code == 410


def test_requests_are_counted_by_verb_and_resource(apiserver: ApiServerDouble):
    name = start_job(apiserver)
    apiserver.run(NAMESPACE, name)
    executor = executor_for(apiserver)
    executor.status(7, 1)
    collect_logs(executor, 7, 1)
    watch_lines(apiserver, f"{PODS}?watch=true&timeoutSeconds=0")
    assert apiserver.counts() == {
        "get jobs": 2,
        "list pods": 1,
        "get pods/log": 1,
        "watch pods": 1,
    }


def test_the_cluster_watch_follows_a_job_to_its_end_with_two_watches(
    apiserver: ApiServerDouble, cluster: ClusterWatch
):
    name = make_spec().name
    woken = cluster.subscribe(name)
    until(lambda: cluster.synced, "the first lists")
    woken.clear()
    start_job(apiserver)
    until(woken.is_set, "the Job's creation to wake its follower")
    apiserver.run(NAMESPACE, name)
    until(lambda: len(cluster.pods_of(name)) == 1, "its pod")
    apiserver.succeed(NAMESPACE, name, ["done"])
    until(lambda: job_status(cluster.job(name)).phase == "succeeded", "its end")  # type: ignore[arg-type]
    apiserver.finish_deletions()
    apiserver.jobs.pop((NAMESPACE, name))
    until(lambda: cluster.job(name) is None, "its deletion")
    made = apiserver.counts()
    assert (made["list jobs"], made["list pods"]) == (1, 1)
    assert set(made) == {"list jobs", "list pods", "watch jobs", "watch pods"}


def test_a_watch_ended_by_its_timeout_resumes_from_its_version_without_listing_again(
    apiserver: ApiServerDouble, cluster: ClusterWatch
):
    until(lambda: apiserver.counts()["watch jobs"] >= 2, "a watch ended and resumed")
    name = start_job(apiserver)
    until(lambda: cluster.job(name) is not None, "the Job")
    watches = [r for r in apiserver.requests if r.query.get("watch") and "/jobs" in r.path]
    assert watches[0].query["resourceVersion"] == watches[1].query["resourceVersion"]
    assert apiserver.counts()["list jobs"] == 1
    assert cluster.jobs.relists == 0


def test_a_410_mid_stream_lists_again_and_the_job_is_still_followed_to_its_end(
    apiserver: ApiServerDouble, cluster: ClusterWatch
):
    name = start_job(apiserver)
    apiserver.run(NAMESPACE, name)
    # Jobs and pods come on two watches: each must have seen the Job's start.
    until(lambda: cluster.job(name) is not None and len(cluster.pods_of(name)) == 1, "its pod")
    with apiserver.together():  # compacted, and the Job ended, before the watch resumed
        apiserver.expire_watches()
        apiserver.succeed(NAMESPACE, name, ["done"])
    until(lambda: job_status(cluster.job(name)).phase == "succeeded", "its end")  # type: ignore[arg-type]
    assert cluster.jobs.relists >= 1
    assert apiserver.counts()["list jobs"] >= 2


def test_an_unreachable_api_server_is_reported_then_forgotten_once_back(
    apiserver: ApiServerDouble, cluster: ClusterWatch
):
    until(lambda: cluster.synced, "the first lists")
    apiserver.expire_watches()  # both watches end and list again...
    # ...and that list fails until the failure has been seen (once, the retry after a jittered
    # back-off could end it before a busy test looked).
    apiserver.fail_next("GET", "/jobs", *[500] * 1000)
    until(lambda: cluster.failing() is not None, "the failure")
    failure = cluster.failing()
    assert failure is not None
    assert "500" in failure.error
    apiserver.clear_faults()
    name = start_job(apiserver)
    until(lambda: cluster.job(name) is not None, "the Job, once the server answers")
    until(lambda: cluster.failing() is None, "the failure forgotten")


def test_a_watch_that_opens_again_after_an_outage_ends_the_failure_before_any_event(
    apiserver: ApiServerDouble,
):
    """Bookmarks come once a minute, the watch's timeout in minutes: the watch opening is the
    sign that the API server is back."""
    cluster = ClusterWatch(executor_for(apiserver), watch_timeout_s=(300.0, 300.0))
    seen: list[Failure] = []

    def pause(stop: threading.Event, seconds: float) -> bool:
        if cluster.jobs.failure is not None:
            seen.append(copy.copy(cluster.jobs.failure))
        return stop.is_set()  # no waiting between tries

    cluster.jobs.pause = pause
    cluster.start()
    try:
        until(lambda: cluster.synced, "the first lists")
        watches = apiserver.counts()["watch jobs"]
        apiserver.fail_next("GET", "/jobs", 503, 503, 503)
        apiserver.cut_watches()  # the API server restarts: its watches end, and it refuses
        until(lambda: cluster.failing() is None and not apiserver.faults, "the failure forgotten")
        assert [f.error for f in seen] == ["503 Service Unavailable"] * 3
        assert apiserver.counts()["watch jobs"] == watches + 4  # the last one open, silent
        assert apiserver.counts()["list jobs"] == 1  # resumed from its version: no list
    finally:
        cluster.close()


def test_a_410_answering_the_resumed_watch_request_lists_again(
    apiserver: ApiServerDouble, cluster: ClusterWatch
):
    until(lambda: apiserver.counts()["watch jobs"] == 1, "the first watch")
    apiserver.fail_next("GET", "/jobs", 410)  # the resumed watch, once the first times out
    until(lambda: cluster.jobs.relists == 1, "a list again")
    name = start_job(apiserver)
    until(lambda: cluster.job(name) is not None, "the Job, followed again")
    made = apiserver.counts()
    assert made["list jobs"] == 2
    assert cluster.failing() is None


def test_what_was_deleted_while_the_watch_had_expired_is_gone_after_the_new_list(
    apiserver: ApiServerDouble, cluster: ClusterWatch
):
    name = start_job(apiserver)
    apiserver.run(NAMESPACE, name)
    until(lambda: len(cluster.pods_of(name)) == 1, "its pod")
    with apiserver.together():  # the deletion's events are compacted away before delivery
        apiserver.exceed_deadline(NAMESPACE, name)
        apiserver.settle(NAMESPACE, name)  # (1.31: its terminating pod goes)
        apiserver.jobs.pop((NAMESPACE, name))
        apiserver.expire_watches()
    until(lambda: cluster.job(name) is None and cluster.pods_of(name) == [], "an empty cache")


def test_the_first_list_follows_its_pages(
    apiserver: ApiServerDouble, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setattr("worker.kubernetes.informer.LIST_PAGE", 2)
    names = [start_job(apiserver, submission_id=sid) for sid in range(1, 6)]
    watch = ClusterWatch(executor_for(apiserver))
    watch.start()
    try:
        until(lambda: watch.synced, "the first lists")
        assert [watch.job(name) is not None for name in names] == [True] * 5
        assert apiserver.counts()["list jobs"] == 3  # 2 + 2 + 1
    finally:
        watch.close()


def test_watches_cut_at_once_are_opened_again_after_a_growing_delay_reset_by_one_that_lasted(
    apiserver: ApiServerDouble,
):
    apiserver.watch_cut_after = 0.0  # a proxy in front of the server cuts every watch at once
    delays: list[float] = []
    resume = threading.Event()
    cluster = ClusterWatch(executor_for(apiserver))

    def pause(stop: threading.Event, seconds: float) -> bool:
        delays.append(seconds)
        if len(delays) == 3:
            resume.wait(30)  # the test looks meanwhile
        elif len(delays) == 5:
            stop.wait()
        return stop.is_set()

    cluster.jobs.pause, cluster.jobs.jitter = pause, lambda: 0.5
    cluster.start()
    try:
        until(lambda: len(delays) == 3, "three watches cut at once")
        assert apiserver.counts()["watch jobs"] == 3  # each one waited for before the next
        start_job(apiserver)  # the next watch brings the Job before it is cut: it lasted
        resume.set()
        until(lambda: len(delays) == 5, "two more watches cut at once")
        assert delays == [0.4, 0.8, 1.6, 0.4, 0.8]  # doubling, jittered, counted again
        assert apiserver.counts()["watch jobs"] == 6
        assert cluster.job(make_spec().name) is not None
    finally:
        cluster.close()


def test_closing_ends_watches_at_once_with_no_event_to_wake_them(apiserver: ApiServerDouble):
    """Between bookmarks (a minute apart) a watch waits on a silent stream: closing shuts its
    socket, so the informers' threads end without an event."""
    cluster = ClusterWatch(executor_for(apiserver), watch_timeout_s=(300.0, 300.0))
    cluster.start()
    until(lambda: cluster.synced, "the first lists")
    until(lambda: apiserver.counts().get("watch pods", 0) >= 1, "the pods' watch open")
    cluster.close()
    threads = cluster._threads
    until(lambda: not any(t.is_alive() for t in threads), "the informers' threads ended")
    assert cluster.failing() is None


def test_closing_while_a_watch_request_is_on_its_way_ends_it_once_answered(
    apiserver: ApiServerDouble,
):
    """`close` may come after a list and before the watch's answer, with no response to shut
    down yet: the watch is shut down as its answer comes, not left open until an event (none
    comes here: the double's clock stands still, so no bookmark either)."""
    cluster = ClusterWatch(executor_for(apiserver), watch_timeout_s=(300.0, 300.0))
    stopped = threading.Event()
    listing, stopping = cluster.jobs.list_call, cluster.jobs.stop

    def sent_after_the_stop(*args: Any, **kwargs: Any) -> Any:
        if kwargs.get("watch"):
            stopped.wait(60)  # the request leaves once `close` has looked for a response
        return listing(*args, **kwargs)

    def stop_then_send() -> None:
        stopping()
        stopped.set()

    sent_after_the_stop.__doc__ = listing.__doc__  # the client reads the type from it
    cluster.jobs.list_call, cluster.jobs.stop = sent_after_the_stop, stop_then_send  # type: ignore[method-assign]
    cluster.start()
    until(lambda: cluster.synced, "the first lists")
    cluster.close()
    thread = cluster._threads[0]
    until(lambda: not thread.is_alive(), "the jobs' informer ended")
    assert apiserver.counts()["watch jobs"] == 1  # it was answered, then shut down
    assert cluster.failing() is None
