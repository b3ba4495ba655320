"""What the cluster holds of our evaluation Jobs and pods, kept current by watches.

One `ClusterWatch` per worker process and cluster follows every evaluation Job and pod of the
namespace (by label) with two list+watch loops (`Informer`), however many attempts the process
watches: the API requests it makes do not grow with the Jobs it follows. Each loop lists once,
then watches from the list's resourceVersion with bookmarks; a watch ends after
`WATCH_TIMEOUT_S` (the server closes it) and resumes from the last version it saw, so a quiet
cluster costs one request per loop every few minutes. A `410 Gone` (the version was compacted
away, in the stream or on the request) lists again and resumes from there; other failures are
retried with backoff and reported by `failing`, so the watchers can tell an outage from a quiet
Job; any request the server answers (a list, a watch that opens) ends the failure, for a watch
may then stay silent for minutes (bookmarks come about once a minute). A watch that ends at once
with nothing in it (a proxy or a restarting server cutting it) is opened again after a back-off
too, so a cut that repeats never becomes a stream of requests.
Followers subscribe by Job name and are woken when their Job or one of its pods changes.
"""

from __future__ import annotations

import functools
import logging
import os
import random
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import urllib3
from kubernetes import watch
from kubernetes.client import ApiException, V1Job, V1Pod

from worker.kubernetes.client import Backoff, KubernetesExecutor, kubernetes_executor
from worker.kubernetes.manifest import (
    APP,
    APP_LABEL,
    ATTEMPT_LABEL,
    ROLE,
    ROLE_LABEL,
    SUBMISSION_LABEL,
    job_name,
)
from worker.settings import WorkerSettings

log = logging.getLogger(__name__)

WATCH_TIMEOUT_S = (300.0, 600.0)
"""Each watch request asks the server to end it after a random time in this range (as
client-go's reflectors do), spreading the renewals of many workers."""
READ_SLACK_S = 60.0  # beyond the watch's own timeout, before a silent connection is dropped
LIST_PAGE = 500
SELECTOR = f"{APP_LABEL}={APP},{ROLE_LABEL}={ROLE}"
EVERYONE = "*"  # `on_change`'s key after a (re-)list: every follower looks again
RETRY = Backoff(attempts=1_000_000, base_s=0.5, cap_s=30.0)
SHORT_WATCH_S = 1.0
REOPEN = Backoff(attempts=1_000_000, base_s=0.8, cap_s=30.0)
"""After a watch that lasted under `SHORT_WATCH_S` and brought no event (not even a bookmark),
the next waits 0.8 s doubling to 30 s, with full jitter; a watch that lasted starts the count
again (as client-go's reflector: "very short watch" in `watchHandler`, and its backoffManager,
in staging/src/k8s.io/client-go/tools/cache/reflector.go)."""


def _wait(stop: threading.Event, seconds: float) -> bool:
    return stop.wait(seconds)


@dataclass
class Failure:
    """Since when (monotonic) a loop cannot list or watch, and the last error."""

    since: float
    error: str


@dataclass
class Informer:
    """A list+watch loop over one kind of object: a cache by name, grouped by `key_of`."""

    kind: str
    list_call: Callable[..., Any]
    namespace: str
    key_of: Callable[[Any], str | None]
    on_change: Callable[[str], None]
    watch_timeout_s: tuple[float, float] = WATCH_TIMEOUT_S
    connect_timeout_s: float = 5.0
    resource_version: str | None = None
    synced: threading.Event = field(default_factory=threading.Event)
    failure: Failure | None = None
    relists: int = 0
    """How many times a `410 Gone` made the loop list again."""
    pause: Callable[[threading.Event, float], bool] = _wait
    """Waits between requests (`stop.wait`; tests record them)."""
    jitter: Callable[[], float] = random.random
    _objects: dict[str, Any] = field(default_factory=dict)
    _by_key: dict[str, dict[str, Any]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _watch: watch.Watch | None = None
    _response: Any = None

    def get(self, key: str) -> list[Any]:
        """The cached objects grouped under `key`."""
        with self._lock:
            return list(self._by_key.get(key, {}).values())

    def run(self, stop: threading.Event) -> None:
        """List, then watch, until `stop`; a 410 lists again, other failures back off."""
        retry = short = 0
        while not stop.is_set():
            try:
                if self.resource_version is None:
                    self._list()
                lasted = self._follow(stop)
                retry, self.failure = 0, None
                short = 0 if lasted else short + 1
                if short and not stop.is_set():
                    self.pause(stop, REOPEN.delay(short - 1, self.jitter(), None))
            except ApiException as exc:
                if exc.status == 410:  # our version was compacted away: list again
                    log.info("the %s watch expired (410 Gone): listing again", self.kind)
                    self.resource_version, self.relists = None, self.relists + 1
                    continue
                retry = self._failed(stop, retry, f"{exc.status} {exc.reason}")
            except (urllib3.exceptions.HTTPError, OSError, ValueError) as exc:
                retry = self._failed(stop, retry, f"{type(exc).__name__}: {exc}")
            except Exception as exc:  # an answer we misread: the loop must live on, and say so
                log.exception("the %s watch broke", self.kind)
                retry = self._failed(stop, retry, f"{type(exc).__name__}: {exc}")

    def stop(self) -> None:
        """Unblock a watch waiting on the server: its socket is shut down, so the read ends at
        once, not at the next event (a minute away between bookmarks). Call it once the event
        its `run` was given is set."""
        current = self._watch
        if current is not None:
            current.stop()  # type: ignore[no-untyped-call]
        _shut_down(self._response)

    def _failed(self, stop: threading.Event, retry: int, error: str) -> int:
        if stop.is_set():  # `stop` shut the watch's socket: no failure of the API's
            return retry
        if self.failure is None:
            self.failure = Failure(time.monotonic(), error)
        else:
            self.failure.error = error
        log.warning("the %s watch failed (retry %d): %s", self.kind, retry + 1, error)
        self.pause(stop, RETRY.delay(retry, self.jitter(), None))
        return retry + 1

    def _list(self) -> None:
        objects: dict[str, Any] = {}
        token: str | None = None
        version = ""
        while True:
            page = self.list_call(
                self.namespace,
                label_selector=SELECTOR,
                limit=LIST_PAGE,
                _continue=token,
                _request_timeout=(self.connect_timeout_s, 60.0),
            )
            meta = page.metadata
            version = version or ((meta.resource_version if meta else None) or "")
            objects.update({o.metadata.name: o for o in page.items if o.metadata})
            token = meta.var_continue if meta else None
            if not token:
                break
        with self._lock:
            self._objects = objects
            self._by_key = {}
            for name, obj in objects.items():
                self._by_key.setdefault(self.key_of(obj) or "", {})[name] = obj
        self.resource_version = version or None
        self.synced.set()
        self.failure = None  # the API server answered: whatever failed before is over
        self.on_change(EVERYONE)  # what changed while unwatched is unknown: everyone looks

    def _follow(self, stop: threading.Event) -> bool:
        """One watch request, from `resource_version` to the server's end of it; whether it
        lasted (`SHORT_WATCH_S`, or brought an event)."""
        began, events = time.monotonic(), 0
        if stop.is_set():  # stopped while listing: no watch to open
            return True
        timeout = int(random.uniform(*self.watch_timeout_s))
        self._watch = watch.Watch()  # type: ignore[no-untyped-call]
        stream = self._watch.stream(  # type: ignore[no-untyped-call]
            _telling_answers(self.list_call, lambda response: self._answered(response, stop)),
            self.namespace,
            label_selector=SELECTOR,
            resource_version=self.resource_version,
            allow_watch_bookmarks=True,
            timeout_seconds=timeout,
            _request_timeout=(self.connect_timeout_s, timeout + READ_SLACK_S),
        )
        try:
            for event in stream:
                if stop.is_set():
                    break
                self._apply(event)
                self.failure, events = None, events + 1
        finally:
            self._watch, self._response = None, None
        return events > 0 or time.monotonic() - began >= SHORT_WATCH_S

    def _answered(self, response: Any, stop: threading.Event) -> None:
        """The API server answered the watch request: whatever failed before is over. Its
        response is kept for `stop`; where `stop` came while the request was on its way, the
        watch is shut down here (`stop` set before `stop()` reads the response: one of the two
        sees the other's), else it would wait for the next event, a minute away."""
        self.failure, self._response = None, response
        if stop.is_set():
            _shut_down(response)

    def _apply(self, event: dict[str, Any]) -> None:
        kind, raw = event["type"], event["raw_object"]
        if kind == "BOOKMARK":  # only the version moves on: nothing of ours changed
            self.resource_version = raw["metadata"]["resourceVersion"]
            return
        obj = event["object"]
        name = obj.metadata.name
        key = self.key_of(obj)
        with self._lock:
            old = self._objects.pop(name, None)
            old_key = self.key_of(old) if old is not None else None
            if old_key is not None:
                self._by_key.get(old_key, {}).pop(name, None)
            if kind != "DELETED":
                self._objects[name] = obj
                self._by_key.setdefault(key or "", {})[name] = obj
        self.resource_version = obj.metadata.resource_version or self.resource_version
        for changed in {key, old_key}:
            if changed:
                self.on_change(changed)


def _telling_answers(
    call: Callable[..., Any], answered: Callable[[Any], None]
) -> Callable[..., Any]:
    """`call` for a watch, calling `answered` once the server has answered the request (its
    status line; an error raises instead): the API is back, whatever the stream brings later.
    Its docstring is kept: the watch reads the return type from it."""

    @functools.wraps(call)
    def answering(*args: Any, **kwargs: Any) -> Any:
        response = call(*args, **kwargs)
        answered(response)
        return response

    return answering


def _shut_down(response: Any) -> None:
    """Shut down the socket a watch's response reads from (through a duplicate of its file
    descriptor: the read's own file stays open for the reading thread to close). The client's
    `Watch.stop` means to, but reaches the socket through the connection, which a response
    the server closes after (`Connection: close`) no longer holds: the read then goes on
    until the next event, a minute away between bookmarks."""
    try:
        descriptor = response.fileno()
    except (AttributeError, OSError, ValueError):  # none, or closed already
        return
    try:
        with socket.socket(fileno=os.dup(descriptor)) as duplicate:
            duplicate.shutdown(socket.SHUT_RDWR)
    except OSError:  # closed meanwhile
        pass


def _job_key(job: V1Job) -> str | None:
    return job.metadata.name if job.metadata is not None else None


def _pod_key(pod: V1Pod) -> str | None:
    """The name of the Job a pod belongs to, from our labels (the manifest sets them)."""
    labels = (pod.metadata.labels if pod.metadata is not None else None) or {}
    submission, attempt = labels.get(SUBMISSION_LABEL, ""), labels.get(ATTEMPT_LABEL, "")
    if not submission.isdigit() or not attempt.isdigit():
        return None
    return job_name(int(submission), int(attempt))


class ClusterWatch:
    """The evaluation Jobs and pods of one namespace, watched once for a whole process."""

    def __init__(
        self,
        executor: KubernetesExecutor,
        *,
        watch_timeout_s: tuple[float, float] = WATCH_TIMEOUT_S,
    ) -> None:
        self.executor = executor
        self._waiters: dict[str, set[threading.Event]] = {}
        self._waiters_lock = threading.Lock()
        self._stop = threading.Event()
        self.jobs = Informer(
            "jobs",
            executor.batch.list_namespaced_job,
            executor.namespace,
            _job_key,
            self._changed,
            watch_timeout_s,
        )
        self.pods = Informer(
            "pods",
            executor.core.list_namespaced_pod,
            executor.namespace,
            _pod_key,
            self._changed,
            watch_timeout_s,
        )
        self._threads = [
            threading.Thread(target=i.run, args=(self._stop,), name=f"k8s-watch-{i.kind}")
            for i in (self.jobs, self.pods)
        ]
        for thread in self._threads:
            thread.daemon = True
        self.users = 0

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        """Stop both loops and release the client's connections."""
        self._stop.set()
        for informer in (self.jobs, self.pods):
            informer.stop()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(timeout=5.0)
        self.executor.close()

    @property
    def synced(self) -> bool:
        """Whether both caches have been listed at least once."""
        return self.jobs.synced.is_set() and self.pods.synced.is_set()

    def failing(self) -> Failure | None:
        """The older failure of the two loops, if either cannot reach the API server now."""
        failures = [f for f in (self.jobs.failure, self.pods.failure) if f is not None]
        return min(failures, key=lambda f: f.since) if failures else None

    def job(self, name: str) -> V1Job | None:
        """The Job as last seen (None: not in the cache, perhaps not yet)."""
        found = self.jobs.get(name)
        return found[0] if found else None

    def pods_of(self, name: str) -> list[V1Pod]:
        """The pods of the Job `name` as last seen."""
        return self.pods.get(name)

    def subscribe(self, name: str) -> threading.Event:
        """An event set whenever the Job `name` or one of its pods changes (set at once)."""
        event = threading.Event()
        event.set()
        with self._waiters_lock:
            self._waiters.setdefault(name, set()).add(event)
        return event

    def unsubscribe(self, name: str, event: threading.Event) -> None:
        with self._waiters_lock:
            waiting = self._waiters.get(name, set())
            waiting.discard(event)
            if not waiting:
                self._waiters.pop(name, None)

    def _changed(self, name: str) -> None:
        with self._waiters_lock:
            if name == EVERYONE:
                waiting = [e for events in self._waiters.values() for e in events]
            else:
                waiting = list(self._waiters.get(name, ()))
        for event in waiting:
            event.set()


_SHARED: dict[tuple[object, ...], ClusterWatch] = {}
_SHARED_LOCK = threading.Lock()


def _key(settings: WorkerSettings) -> tuple[object, ...]:
    return (
        settings.k8s_api_url,
        settings.k8s_in_cluster,
        str(settings.k8s_kubeconfig),
        settings.k8s_namespace,
    )


def running_watch(settings: WorkerSettings) -> ClusterWatch | None:
    """The process's watch of the configured cluster, if one runs now."""
    with _SHARED_LOCK:
        return _SHARED.get(_key(settings))


@contextmanager
def cluster_watch(settings: WorkerSettings) -> Iterator[ClusterWatch]:
    """The process's watch of the configured cluster, started on first use and stopped when
    its last follower leaves."""
    key = _key(settings)
    with _SHARED_LOCK:
        shared = _SHARED.get(key)
        if shared is None:
            shared = ClusterWatch(kubernetes_executor(settings))
            shared.start()
            _SHARED[key] = shared
        shared.users += 1
    try:
        yield shared
    finally:
        with _SHARED_LOCK:
            shared.users -= 1
            last = shared.users == 0
            if last:
                del _SHARED[key]
        if last:
            shared.close()
