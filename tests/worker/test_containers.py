"""The docker executor against Podman's Docker API, with real images pulled from a registry."""

from __future__ import annotations

import dataclasses
import itertools
import os
import random
import socket
import stat
import textwrap
import time
import uuid
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import pytest
from docker.errors import ImageNotFound
from docker.types import DeviceRequest, Mount

from evaluator.endpoint import PolicyEndpoint
from evaluator.evaluation import evaluate
from evaluator.plan import EvaluationPlan, build_plan
from evaluator.results import EvaluationResult, episode_records
from evaluator.sources import LocalDirectory
from evaluator.suite import load_suite
from tests.evaluator.conftest import SCRIPTED, tiny_plan, with_limits
from tests.server.registry_fixture import fixture_registry  # noqa: F401 - pytest fixture
from tests.worker.container_fixtures import (  # noqa: F401 - pytest fixtures
    ContainerEngine,
    PolicyImages,
    fixture_container_engine,
    fixture_policy_images,
    policy_containers,
    session_tag,
    untag,
)
from tests.worker.docker_double import docker_double
from worker.containers import (
    POLICY_UID,
    SOCKET_MOUNT,
    ContainerImage,
    ContainerLimits,
    ContainerProcess,
    ExecutorError,
    attempt_key,
    container_config,
    container_endpoint,
    exit_detail,
    gpu_refusal,
    pinned_reference,
    remove_leftovers,
    share_socket,
)

pytestmark = pytest.mark.long

DIGEST = "sha256:" + "ab" * 32
LIMITS = ContainerLimits(memory_mib=256, cpus=1.0, pids=64, tmpfs_mib=16)

HEADER = """\
import os, socket, sys, time
from manieval_sdk import Policy, serve
"""
SLEEPER = HEADER + 'print("sleeping", flush=True)\ntime.sleep(3600)\n'


# This session's service, as the reconciler knows it: others on the machine have their own.
SERVICE = f"test-session-{uuid.uuid4().hex[:8]}"


@pytest.fixture(scope="module")
def attempts() -> Iterator[tuple[int, int]]:
    """(submission, attempt) pairs no other test or session on this machine uses."""
    start = random.randrange(10**6, 10**9)
    return ((n, 1) for n in itertools.count(start))


def container_source(
    image: str,
    ids: tuple[int, int],
    container_engine: ContainerEngine,
    limits: ContainerLimits = LIMITS,
) -> ContainerImage:
    submission, attempt = ids
    return ContainerImage(
        image,
        submission=submission,
        attempt=attempt,
        engine_url=container_engine.url,
        limits=limits,
        service=SERVICE,
    )


def hostile_plan() -> EvaluationPlan:
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=2)
    return with_limits(plan, connect_timeout_s=30, first_call_timeout_s=5, call_timeout_s=2)


def evaluate_hostile(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    ids: tuple[int, int],
    name: str,
    body: str,
) -> EvaluationResult:
    """Evaluate a hostile policy in a container; it must be given up on in bounded time."""
    image = policy_images.publish(name, HEADER + textwrap.dedent(body))
    # Given up on, not hung: a hang fails by the suite's timeout (pytest-timeout), and each test
    # asserts which limit ended the episodes. No wall-clock bound: a busy machine is slow.
    result = evaluate(hostile_plan(), container_source(image, ids, container_engine))
    assert policy_containers(container_engine, submission=ids[0], attempt=ids[1]) == []
    return result


def assert_aborted(result: EvaluationResult, kind: str, *reasons: str) -> None:
    assert result.status == "aborted"
    assert result.abort is not None
    assert result.abort.kind == kind
    for reason in reasons:
        assert reason in result.abort.reason


# Pure parts: no engine needed.


def test_container_config_locks_the_policy_down() -> None:
    config = container_config(
        image=f"registry.example/team/policy@{DIGEST}",
        name="manieval-7-2-abcd",
        labels={"manieval.role": "policy"},
        limits=ContainerLimits(memory_mib=512, cpus=1.5, pids=128, tmpfs_mib=32),
        socket_dir=Path("/tmp/manieval-x"),
        endpoint=f"unix://{SOCKET_MOUNT}/policy.sock",
    )
    assert config["network_mode"] == "none"
    assert config["read_only"] is True
    assert config["cap_drop"] == ["ALL"]
    assert config["security_opt"] == ["no-new-privileges"]
    assert config["user"] == f"{POLICY_UID}:{POLICY_UID}"
    assert config["mem_limit"] == config["memswap_limit"] == 512 << 20
    assert config["nano_cpus"] == 1_500_000_000
    assert config["pids_limit"] == 128
    assert config["tmpfs"]["/tmp"] == "size=32m,mode=1777"
    assert all("size=" in options for options in config["tmpfs"].values())
    assert config["mounts"] == [Mount(SOCKET_MOUNT, "/tmp/manieval-x", type="bind", read_only=True)]
    assert "volumes" not in config
    assert "privileged" not in config
    assert config["environment"]["MANIEVAL_ENDPOINT"] == f"unix://{SOCKET_MOUNT}/policy.sock"
    assert {u["Name"] for u in config["ulimits"]} == {"nofile", "nproc"}
    assert config["log_config"]["Config"] == {"max-size": "1m"}


def test_a_gpu_is_requested_as_docker_run_gpus_does_and_only_when_asked_for() -> None:
    def config(gpus: int) -> dict[str, object]:
        return container_config(
            image=f"registry.example/team/policy@{DIGEST}",
            name="manieval-7-2-abcd",
            labels={},
            limits=LIMITS,
            socket_dir=Path("/tmp/manieval-x"),
            endpoint=f"unix://{SOCKET_MOUNT}/policy.sock",
            gpus=gpus,
        )

    assert "device_requests" not in config(0)
    assert config(2)["device_requests"] == [DeviceRequest(count=2, capabilities=[["gpu"]])]
    assert {k: v for k, v in config(2).items() if k != "device_requests"} == config(0)


def test_the_engine_receives_the_gpu_request_on_the_policy_container() -> None:
    endpoint = PolicyEndpoint()
    with docker_double() as (url, recorded), closing(endpoint):
        image = f"127.0.0.1:5000/a/b@{DIGEST}"
        source = ContainerImage(image, submission=1, attempt=1, engine_url=url, gpus=1)
        process = source.launch(endpoint=endpoint.address, socket_dir=endpoint.socket_dir)
        process.stop()
    host = recorded.created()["HostConfig"]
    assert host["DeviceRequests"] == [
        {"Driver": "", "Count": 1, "DeviceIDs": [], "Capabilities": [["gpu"]], "Options": {}}
    ]
    assert host["NetworkMode"] == "none"  # the rest of the sandbox, unchanged
    assert host["ReadonlyRootfs"] is True


def test_an_engine_that_would_drop_a_gpu_request_is_named() -> None:
    docker = [{"Name": "Engine", "Version": "24.0.7"}]
    podman = [{"Name": "Podman Engine", "Version": "4.3.1"}, {"Name": "Conmon"}]
    assert gpu_refusal(docker) is None
    assert "Podman, whose Docker API ignores GPU requests" in str(gpu_refusal(podman))


def test_only_images_pinned_by_digest_are_accepted() -> None:
    assert pinned_reference(f"127.0.0.1:5000/a/b@{DIGEST}") == f"127.0.0.1:5000/a/b@{DIGEST}"
    for reference in ("a/b:latest", "a/b", f"a/b@sha256:{'ab' * 31}", f"a/b:{DIGEST}"):
        with pytest.raises(ValueError, match="pinned by digest"):
            ContainerImage(reference, submission=1, attempt=1)


def test_endpoint_is_translated_into_the_socket_mount() -> None:
    socket_dir = Path("/tmp/manieval-abc")
    inside = container_endpoint(f"unix://{socket_dir}/policy.sock", socket_dir)
    assert inside == f"unix://{SOCKET_MOUNT}/policy.sock"
    with pytest.raises(ExecutorError):
        container_endpoint("unix:///elsewhere/policy.sock", socket_dir)
    with pytest.raises(ExecutorError):
        container_endpoint("tcp://127.0.0.1:5555", socket_dir)


def test_exit_detail_names_the_memory_limit_as_the_sandbox_does() -> None:
    assert exit_detail(exit_code=0, oom_killed=False, memory_mib=256) is None
    assert exit_detail(exit_code=3, oom_killed=False, memory_mib=256) == "exit code 3"
    assert (
        exit_detail(exit_code=137, oom_killed=True, memory_mib=256)
        == "the container engine stopped it at its memory limit of 256 MiB"
    )
    assert (  # Podman 4 on cgroup v1 never says OOMKilled
        exit_detail(exit_code=137, oom_killed=False, memory_mib=64)
        == "the container engine stopped it at its memory limit of 64 MiB"
    )


@pytest.mark.skipif(os.geteuid() != 0, reason="handing files to another gid needs root")
def test_socket_is_shared_with_the_policy_group_only() -> None:
    endpoint = PolicyEndpoint()
    try:
        share_socket(endpoint.socket_dir, endpoint.path)
        directory, sock = endpoint.socket_dir.stat(), endpoint.path.stat()
        assert (directory.st_uid, directory.st_gid) == (os.geteuid(), POLICY_UID)
        assert stat.S_IMODE(directory.st_mode) == 0o710
        assert (sock.st_uid, sock.st_gid) == (os.geteuid(), POLICY_UID)
        assert stat.S_IMODE(sock.st_mode) == 0o660
    finally:
        endpoint.close()


# Against the engine.


@pytest.mark.sim
def test_scripted_policy_scores_the_same_in_a_container_as_in_process(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    plan = build_plan(
        load_suite("maniskill-core"),
        "dev",
        tasks=["PickCube-v1", "PushCube-v1"],
        conditions=["nominal"],
        episodes=3,
    )
    image = policy_images.publish("scripted", (SCRIPTED / "policy.py").read_text())
    ids = next(attempts)
    in_container = evaluate(plan, container_source(image, ids, container_engine))
    in_process = evaluate(plan, LocalDirectory(SCRIPTED))
    assert in_container.status == "completed", in_container.abort
    assert in_container.policy == f"image:{image}"
    assert episode_records(in_container) == episode_records(in_process)
    assert in_container.score == in_process.score > 0
    assert policy_containers(container_engine, submission=ids[0], attempt=ids[1]) == []


def test_a_sessions_cleanup_leaves_another_sessions_equal_image_in_the_store(
    container_engine: ContainerEngine, policy_images: PolicyImages
) -> None:
    """What failed on fresh machines: another session's equal build (the build cache gives it
    this session's template image) is pushed and pulled by digest, and its cleanup asked Podman
    to remove `REPO@DIGEST`, which finds the template's image by that digest and deleted it."""
    other = f"localhost/manieval-test/other-session:{session_tag()}"
    container_engine.podman("tag", policy_images.template, other)
    remote = f"{policy_images.registry.domain}/manieval-test/other-session"
    digest_file = policy_images.work / "other-session.digest"
    container_engine.podman(
        *("push", "--quiet", "--tls-verify=false", "--digestfile", str(digest_file)),
        *(other, f"docker://{remote}:latest"),
    )
    pinned = f"{remote}@{digest_file.read_text().strip()}"
    container_engine.podman("pull", "--quiet", "--tls-verify=false", pinned)
    # All the other session's names, and a digest reference that names no image at all.
    untag(container_engine.env, other, pinned, f"{remote}-never-pulled@{pinned.split('@')[1]}")
    with closing(container_engine.client()) as client:
        assert policy_images.template in client.images.get(policy_images.template).tags
        with pytest.raises(ImageNotFound):
            client.images.get(other)


def test_image_is_pulled_from_the_registry_by_digest(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    # An image of this test's own (built --no-cache: no other session has it), so that taking
    # it out of the store leaves every other session's images where they are.
    image = policy_images.publish("pulled-by-digest", SLEEPER)
    local = policy_images.local_tag("pulled-by-digest")
    with closing(container_engine.client()) as client:
        own = client.images.get(local).id  # by its name: a digest may find another's image
        untag(container_engine.env, local, image)
        container_engine.podman("image", "rm", own)  # no name left, no force needed
        with pytest.raises(ImageNotFound):
            client.images.get(image)
        container_source(image, next(attempts), container_engine).pull()
        assert image in client.images.get(image).attrs["RepoDigests"]


@pytest.mark.sim
def test_the_containers_output_is_passed_on_as_it_comes_to_whoever_asks(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    body = 'print("loading weights", flush=True)\nsys.exit("no weights here")\n'
    image = policy_images.publish("chatty-crasher", HEADER + body)
    pieces: list[tuple[int, bytes]] = []
    result = evaluate(
        hostile_plan(),
        container_source(image, next(attempts), container_engine),
        on_output=lambda shard, data: pieces.append((shard, data)),
    )
    assert_aborted(result, "policy_crashed", "exited before connecting")
    assert {shard for shard, _ in pieces} == {0}
    assert b"".join(data for _, data in pieces) == b"loading weights\nno weights here\n"


def test_podman_is_refused_a_gpu_policy_rather_than_run_it_without_the_gpu(
    container_engine: ContainerEngine, attempts: Iterator[tuple[int, int]]
) -> None:
    ids = next(attempts)
    source = dataclasses.replace(
        container_source(f"127.0.0.1:5000/a/b@{DIGEST}", ids, container_engine), gpus=1
    )
    with pytest.raises(ExecutorError, match="Podman, whose Docker API ignores GPU requests"):
        source.pull()
    with closing(PolicyEndpoint()) as endpoint, pytest.raises(ExecutorError, match="Podman"):
        source.launch(endpoint=endpoint.address, socket_dir=endpoint.socket_dir)
    assert policy_containers(container_engine, submission=ids[0], attempt=ids[1]) == []


@pytest.mark.sim
def test_policy_that_reaches_for_the_network_gets_nowhere(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    listener = socket.create_server(("0.0.0.0", 0))
    listener.setblocking(False)
    port = listener.getsockname()[1]
    targets = [(_host_address(), port), ("127.0.0.1", port), ("1.1.1.1", 443)]
    body = f"""
    for host, port in {targets!r}:
        try:
            socket.create_connection((host, port), timeout=3).close()
            print(f"reached {{host}}:{{port}}", flush=True)
        except OSError as exc:
            print(f"cannot reach {{host}}:{{port}}: {{exc}}", flush=True)
    try:
        socket.getaddrinfo("deb.debian.org", 80)
        print("resolved a name", flush=True)
    except OSError as exc:
        print(f"no name resolution: {{exc}}", flush=True)
    sys.exit("this policy needs the network")
    """
    with listener:
        result = evaluate_hostile(container_engine, policy_images, next(attempts), "network", body)
        with pytest.raises(BlockingIOError):
            listener.accept()  # nothing got through to the host
    assert_aborted(result, "policy_crashed", "exited before connecting", "exit code 1")
    assert result.abort is not None
    assert "Network is unreachable" in result.abort.log_tail
    assert "no name resolution" in result.abort.log_tail
    assert "reached" not in result.abort.log_tail


@pytest.mark.sim
def test_fork_bomb_is_held_by_the_process_limit(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    body = """
    class ForkBomb(Policy):
        def act(self, obs):
            told = False
            while True:
                try:
                    os.fork()
                except OSError as exc:
                    if not told:
                        print(f"fork failed: {exc}", file=sys.stderr, flush=True)
                        told = True
                    time.sleep(0.01)

    serve(ForkBomb())
    """
    result = evaluate_hostile(container_engine, policy_images, next(attempts), "forkbomb", body)
    assert_aborted(  # named as the sandbox names it (evaluator/limits.py)
        result,
        "process_limit",
        "no answer to 'act'",
        f"the container engine stopped it at its limit of {LIMITS.pids} processes",
    )
    assert result.abort is not None
    assert "Resource temporarily unavailable" in result.abort.log_tail


@pytest.mark.sim
def test_memory_hog_is_killed_and_the_reason_names_the_limit(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    body = """
    class Hog(Policy):
        def act(self, obs):
            hoard = []
            while True:
                hoard.append(b"\\1" * (8 << 20))

    serve(Hog())
    """
    result = evaluate_hostile(container_engine, policy_images, next(attempts), "memoryhog", body)
    assert_aborted(  # named as the sandbox names it (evaluator/limits.py)
        result,
        "memory_limit",
        "closed the connection during 'act'",
        "the container engine stopped it at its memory limit of 256 MiB",
    )


@pytest.mark.sim
def test_disk_filler_finds_no_room_and_its_crash_is_reported(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    body = f"""
    class Filler(Policy):
        def act(self, obs):
            for path in ("/opt/policy/fill", "{SOCKET_MOUNT}/fill", "/var/tmp/fill", "/tmp/fill"):
                try:
                    with open(path, "wb") as out:
                        while True:
                            out.write(bytes(1 << 20))
                except OSError as exc:
                    print(f"cannot fill {{path}}: {{exc}}", file=sys.stderr, flush=True)
            os._exit(5)

    serve(Filler())
    """
    result = evaluate_hostile(container_engine, policy_images, next(attempts), "diskfiller", body)
    assert_aborted(result, "policy_crashed", "closed the connection during 'act'", "exit code 5")
    assert result.abort is not None
    tail = result.abort.log_tail
    assert "cannot fill /opt/policy/fill: [Errno 30] Read-only file system" in tail
    assert f"cannot fill {SOCKET_MOUNT}/fill" in tail
    assert "cannot fill /var/tmp/fill: [Errno 28] No space left on device" in tail
    assert "cannot fill /tmp/fill: [Errno 28] No space left on device" in tail


@pytest.mark.sim
def test_cancelled_evaluation_leaves_no_container(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    image = policy_images.publish("scripted", (SCRIPTED / "policy.py").read_text())
    ids = next(attempts)
    done: list[object] = []
    result = evaluate(
        tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=3),
        container_source(image, ids, container_engine),
        on_episode=lambda _run, episode: done.append(episode),
        should_stop=lambda: bool(done),
    )
    failures = [e.failure for e in result.conditions[0].tasks[0].episodes]
    assert failures == [None, "not_run", "not_run"]
    assert policy_containers(container_engine, submission=ids[0], attempt=ids[1]) == []


def test_stop_removes_the_container_and_keeps_its_output(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    ids = next(attempts)
    source = container_source(policy_images.publish("sleeper", SLEEPER), ids, container_engine)
    endpoint = PolicyEndpoint()
    process = source.launch(endpoint=endpoint.address, socket_dir=endpoint.socket_dir)
    try:
        _wait_for_output(process, "sleeping")
        assert process.alive()
        assert process.exit_code() is None
    finally:
        endpoint.close()
        process.stop()
    process.stop()  # idempotent
    assert not process.alive()
    assert process.exit_detail() is None  # we killed it: not the policy's doing
    assert "sleeping" in process.log_tail()
    assert policy_containers(container_engine, submission=ids[0], attempt=ids[1]) == []


def test_reconciler_removes_containers_a_crashed_worker_left(
    container_engine: ContainerEngine,
    policy_images: PolicyImages,
    attempts: Iterator[tuple[int, int]],
) -> None:
    image = policy_images.publish("sleeper", SLEEPER)
    crashed, live = next(attempts), next(attempts)
    endpoints = [PolicyEndpoint(), PolicyEndpoint()]
    processes = [
        container_source(image, ids, container_engine).launch(
            endpoint=endpoint.address, socket_dir=endpoint.socket_dir
        )
        for ids, endpoint in zip((crashed, live), endpoints, strict=True)
    ]
    try:
        with closing(container_engine.client()) as client:
            keep = {attempt_key(*live)}
            assert remove_leftovers(client, service=SERVICE, keep=keep) == []  # too young to judge
            # Another service's containers on the same engine are never this reconciler's.
            assert remove_leftovers(client, service=f"{SERVICE}-other", keep=set(), grace_s=0) == []
            removed = remove_leftovers(client, service=SERVICE, keep=keep, grace_s=0)
            assert removed == [processes[0].name]
            assert (
                policy_containers(container_engine, submission=crashed[0], attempt=crashed[1]) == []
            )
            assert (
                len(policy_containers(container_engine, submission=live[0], attempt=live[1])) == 1
            )
    finally:
        for endpoint, process in zip(endpoints, processes, strict=True):
            endpoint.close()
            process.stop()


def _wait_for_output(process: ContainerProcess, text: str) -> None:
    deadline = time.monotonic() + 30
    while text not in process.log_tail():
        assert time.monotonic() < deadline, process.log_tail()
        time.sleep(0.1)


def _host_address() -> str:
    """This machine's address on its default route (a UDP connect sends nothing)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))
            address: str = probe.getsockname()[0]
        except OSError:
            address = "127.0.0.1"
    return address
