"""The docker executor: a policy image run as a locked-down container next to the evaluator.

Talks to any Docker-API engine (Docker, or Podman's API service) through the `docker` SDK. The
evaluator stays in the trusted worker; the policy container gets no network, a read-only root
filesystem, small tmpfs mounts, no capabilities, no new privileges, a non-root user, memory,
CPU and process limits, and one read-only mount: the directory holding the evaluator's socket.
Containers carry labels naming their submission and attempt, and are always removed: by
`ContainerProcess.stop()` on every way out of an evaluation, and by `remove_leftovers` (the
reconciler) after a worker crash.
"""

from __future__ import annotations

import logging
import os
import re
import secrets
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from docker.client import DockerClient
from docker.errors import DockerException, ImageNotFound, NotFound
from docker.models.containers import Container
from docker.types import DeviceRequest, LogConfig, Mount, Ulimit

from evaluator.limits import ENGINE, Breach, LimitKind, memory_breach, process_breach
from evaluator.sources import LOG_TAIL_BYTES, OutputEcho, OutputSink
from internal_api.schemas import IMAGE_DIGEST, PINNED_IMAGE

log = logging.getLogger(__name__)

DEFAULT_ENGINE_URL = "unix:///run/manieval/podman.sock"  # docker/podman-setup.sh serves it
POLICY_UID = 65532  # the `policy` user of docker/policy-base; never a uid of the worker host
SOCKET_MOUNT = "/run/manieval"  # where the socket directory appears inside the container
LABEL_SUBMISSION = "manieval.submission"
LABEL_ATTEMPT = "manieval.attempt"
LABEL_ROLE = "manieval.role"
LABEL_CREATED = "manieval.created"
LABEL_SERVICE = "manieval.service"
"""The service a container evaluates for (`WorkerSettings.service_id`): the reconciler of one
service never removes another's containers from an engine they share (two services, or two
test sessions, on one machine share rootful Podman's store)."""
ROLE_POLICY = "policy"
LOG_SIZE_MAX = "1m"  # what the engine keeps of the policy's output on its disk
ENGINE_TIMEOUT_S = 60
STOP_GRACE_S = 1.0  # a policy told to close normally exits well within this
POLL_INTERVAL_S = 0.25
SIGKILL_EXIT = 137
MIB = 1 << 20
# repo@sha256:<digest> (what the server pins), or a bare image ID (what `manieval evaluate
# --image` pins a local image to): both name immutable content.
_IMAGE_ID = re.compile(IMAGE_DIGEST)


class ExecutorError(RuntimeError):
    """The engine could not pull or start the policy: our side, not the policy's."""


@dataclass(frozen=True)
class ContainerLimits:
    """What one policy container may use."""

    memory_mib: int = 2048
    cpus: float = 1.0
    pids: int = 256
    tmpfs_mib: int = 64
    open_files: int = 1024
    # RLIMIT_NPROC counts every process of POLICY_UID on the host, across containers; the pids
    # limit is what bounds one container, this only has to stay under the engine's own limit.
    user_processes: int = 8192


def _pinned(image: str) -> bool:
    return PINNED_IMAGE.fullmatch(image) is not None or _IMAGE_ID.fullmatch(image) is not None


def pinned_reference(image: str) -> str:
    """`image` if it names exactly one manifest (`repo@sha256:<hex>`); ValueError otherwise."""
    if not _pinned(image):
        raise ValueError(f"the docker executor runs images pinned by digest only, not {image!r}")
    return image


def pin_local(client: DockerClient, image: str) -> str:
    """Pin a reference the engine knows (a local tag, say) to what it names right now: its
    registry digest when it has one, else its image ID."""
    if _pinned(image):
        return image
    try:
        found = client.images.get(image)
    except ImageNotFound:
        raise ExecutorError(f"the engine has no image {image!r}; build or pull it first") from None
    digests = [d for d in found.attrs.get("RepoDigests") or [] if _pinned(d)]
    return str(digests[0] if digests else found.id)


def attempt_key(submission: int | str, attempt: int | str) -> str:
    """How `remove_leftovers` names an attempt whose containers must be kept."""
    return f"{submission}/{attempt}"


def policy_labels(*, service: str, submission: int, attempt: int, created: float) -> dict[str, str]:
    """Labels that tie a container to its service and attempt, for the reconciler."""
    return {
        LABEL_SERVICE: service,
        LABEL_SUBMISSION: str(submission),
        LABEL_ATTEMPT: str(attempt),
        LABEL_ROLE: ROLE_POLICY,
        LABEL_CREATED: str(int(created)),
    }


def container_name(*, submission: int, attempt: int, token: str) -> str:
    """`manieval-<submission>-<attempt>-<token>`: one attempt may run several policy shards."""
    return f"manieval-{submission}-{attempt}-{token}"


def container_endpoint(endpoint: str, socket_dir: Path) -> str:
    """The evaluator's `unix://` endpoint as the policy sees it through the socket mount."""
    prefix = "unix://"
    path = Path(endpoint.removeprefix(prefix))
    if not endpoint.startswith(prefix) or path.parent != socket_dir:
        raise ExecutorError(f"the docker executor needs a unix socket in {socket_dir}: {endpoint}")
    return f"{prefix}{SOCKET_MOUNT}/{path.name}"


def container_config(
    *,
    image: str,
    name: str,
    labels: Mapping[str, str],
    limits: ContainerLimits,
    socket_dir: Path,
    endpoint: str,
    gpus: int = 0,
) -> dict[str, Any]:
    """Keyword arguments for `containers.create`: the policy's sandbox (pure, no I/O), with
    `gpus` GPUs requested as `docker run --gpus N` does."""
    memory = limits.memory_mib * MIB
    config: dict[str, Any] = {
        "image": image,
        "name": name,
        "labels": dict(labels),
        "environment": {"MANIEVAL_ENDPOINT": endpoint, "HOME": "/tmp", "PYTHONUNBUFFERED": "1"},
        "user": f"{POLICY_UID}:{POLICY_UID}",
        "network_mode": "none",
        "read_only": True,
        # Podman mounts unbounded tmpfs on /run and /var/tmp of read-only containers: bound them.
        "tmpfs": {
            "/tmp": f"size={limits.tmpfs_mib}m,mode=1777",
            "/var/tmp": "size=1m,mode=1777",
            "/run": "size=1m,mode=755",
        },
        "shm_size": limits.tmpfs_mib * MIB,
        "mounts": [Mount(SOCKET_MOUNT, str(socket_dir), type="bind", read_only=True)],
        "cap_drop": ["ALL"],
        "security_opt": ["no-new-privileges"],
        "mem_limit": memory,
        "memswap_limit": memory,
        "nano_cpus": int(limits.cpus * 1e9),
        "pids_limit": limits.pids,
        "ulimits": [
            Ulimit(name="nofile", soft=limits.open_files, hard=limits.open_files),
            Ulimit(name="nproc", soft=limits.user_processes, hard=limits.user_processes),
        ],
        # As PID 1, python ignores SIGTERM: any stop is a kill, at once.
        "stop_signal": "SIGKILL",
        "log_config": LogConfig(type="json-file", config={"max-size": LOG_SIZE_MAX}),
        "stdin_open": False,
        "tty": False,
    }
    if gpus:
        config["device_requests"] = [DeviceRequest(count=gpus, capabilities=[["gpu"]])]
    return config


def share_socket(socket_dir: Path, socket_path: Path, *, gid: int = POLICY_UID) -> None:
    """Let the policy's group, and no one else but us, reach the socket: 0710 dir, 0660 socket."""
    try:
        os.chown(socket_dir, -1, gid)
        os.chown(socket_path, -1, gid)
    except PermissionError:
        # Not root: the container's uid is not ours to hand files to, so open them to all.
        log.warning("cannot give %s to gid %d: opening it to every local user", socket_dir, gid)
        os.chmod(socket_dir, 0o711)
        os.chmod(socket_path, 0o666)
        return
    os.chmod(socket_dir, 0o710)
    os.chmod(socket_path, 0o660)


def memory_killed(*, exit_code: int, oom_killed: bool) -> bool:
    """Whether a container that ended on its own was killed at its memory limit."""
    # Podman 4 on cgroup v1 never sets OOMKilled; nothing but the kernel kills PID 1 here.
    return oom_killed or exit_code == SIGKILL_EXIT


def exit_detail(*, exit_code: int, oom_killed: bool, memory_mib: int) -> str | None:
    """How a container that ended on its own ended, in words for the submission's owner."""
    if memory_killed(exit_code=exit_code, oom_killed=oom_killed):
        return memory_breach(ENGINE, memory_mib).detail
    return None if exit_code == 0 else f"exit code {exit_code}"


_api_versions: dict[str, str] = {}  # engine URL -> API version it speaks


def engine(url: str) -> DockerClient:
    """A client of the Docker-API engine at `url`."""
    # Asking for the version takes Podman 4 a second: once per engine and process is enough.
    client = DockerClient(base_url=url, version=_api_versions.get(url), timeout=ENGINE_TIMEOUT_S)
    _api_versions[url] = client.api.api_version
    return client


def gpu_refusal(components: list[dict[str, Any]]) -> str | None:
    """Why the engine whose `/version` lists these components cannot give a container GPUs,
    or None."""
    if any(str(c.get("Name", "")).startswith("Podman") for c in components):
        # It accepts the request and starts the container without the GPU (podman#22645).
        return (
            "the container engine is Podman, whose Docker API ignores GPU requests: run "
            "policies that need a GPU on Docker with the NVIDIA Container Toolkit, or on "
            "Kubernetes (docs/deploy.md, GPUs for policies)"
        )
    return None


def ensure_gpus(client: DockerClient, gpus: int) -> None:
    """ExecutorError unless the engine can give a container `gpus` GPUs (0: nothing to do)."""
    if gpus:
        refusal = gpu_refusal(client.version().get("Components") or [])
        if refusal is not None:
            raise ExecutorError(refusal)


def ensure_image(client: DockerClient, image: str) -> None:
    """Pull `image` unless the engine has it (a digest names immutable content)."""
    try:
        client.images.get(image)
    except ImageNotFound:
        log.info("pulling %s", image)
        client.images.pull(image)


@dataclass(frozen=True)
class ContainerImage:
    """A policy image pinned by digest, run by the engine at `engine_url` for one attempt."""

    image: str
    submission: int
    attempt: int
    engine_url: str = DEFAULT_ENGINE_URL
    limits: ContainerLimits = field(default_factory=ContainerLimits)
    service: str = ""
    """The service it evaluates for (`WorkerSettings.service_id`; "": a local `evaluate`)."""
    gpus: int = 0
    """GPUs the container gets (the suite's `policy.gpus`), requested as `--gpus N` does."""

    def __post_init__(self) -> None:
        pinned_reference(self.image)

    def describe(self) -> str:
        """How the result document names this policy."""
        return f"image:{self.image}"

    def pinned_image(self) -> str:
        """The image, pinned by digest (or a local image's ID)."""
        return self.image

    def pull(self) -> None:
        """Fetch the image ahead of the evaluation, so its time is not the policy's."""
        client = engine(self.engine_url)
        try:
            ensure_gpus(client, self.gpus)
            ensure_image(client, self.image)
        except DockerException as exc:
            raise ExecutorError(f"cannot pull {self.image}: {exc}") from exc
        finally:
            client.close()

    def launch(self, *, endpoint: str, socket_dir: Path) -> ContainerProcess:
        """Start the policy container; it connects to `endpoint` through the socket mount."""
        inside = container_endpoint(endpoint, socket_dir)
        share_socket(socket_dir, socket_dir / Path(inside).name)
        config = container_config(
            image=self.image,
            name=container_name(
                submission=self.submission, attempt=self.attempt, token=secrets.token_hex(4)
            ),
            labels=policy_labels(
                service=self.service,
                submission=self.submission,
                attempt=self.attempt,
                created=time.time(),
            ),
            limits=self.limits,
            socket_dir=socket_dir,
            endpoint=inside,
            gpus=self.gpus,
        )
        client = engine(self.engine_url)
        try:
            ensure_gpus(client, self.gpus)
            ensure_image(client, self.image)
            container = client.containers.create(**config)
        except ExecutorError:
            client.close()
            raise
        except DockerException as exc:
            client.close()
            raise ExecutorError(f"cannot create a container of {self.image}: {exc}") from exc
        try:
            container.start()
        except DockerException as exc:
            _remove(container)
            client.close()
            raise ExecutorError(f"cannot start {config['name']}: {exc}") from exc
        return ContainerProcess(client, container, limits=self.limits, engine_url=self.engine_url)


class ContainerProcess:
    """A running policy container: its state, output and removal through the engine's API."""

    def __init__(
        self,
        client: DockerClient,
        container: Container,
        *,
        limits: ContainerLimits,
        engine_url: str = DEFAULT_ENGINE_URL,
    ) -> None:
        self._client = client
        self._container = container
        self._engine_url = engine_url
        self._echo: threading.Thread | None = None
        self.name = str(container.name)
        self._limits = limits
        self._lock = threading.Lock()
        self._polled = -float("inf")
        self._state: dict[str, Any] | None = None  # the engine's State once it stopped running
        self._detail: str | None = None
        self._breach: Breach | None = None
        self._tail: str | None = None
        self._stopped = False

    def alive(self) -> bool:
        """Whether the container still runs (asks the engine at most every POLL_INTERVAL_S)."""
        return self._ended(max_age=POLL_INTERVAL_S) is None

    def exit_code(self) -> int | None:
        """The container's exit code, None while it runs."""
        state = self._ended(max_age=POLL_INTERVAL_S)
        code = None if state is None else state.get("ExitCode")
        return None if code is None else int(code)

    def exit_detail(self) -> str | None:
        """After stop(): how it ended if it ended on its own (memory limit, exit code), or the
        limit it was held at."""
        return self._breach.detail if self._breach is not None else self._detail

    def limit_reached(self) -> LimitKind | None:
        """After stop(): the limit the engine held it at (`ConfinedProcess`): killed at its
        memory limit, or running as many processes as its pids limit lets it (a fork bomb the
        engine refuses more, which then answers nothing)."""
        return self._breach.kind if self._breach is not None else None

    def log_tail(self) -> str:
        """The last bytes of the policy's stdout and stderr (kept after the container is gone)."""
        return self._tail if self._tail is not None else self._read_logs()

    def echo(self, sink: OutputSink) -> None:
        """Pass the container's output on to `sink` as it comes, from its start (see
        `evaluator.sources.EchoingProcess`), until the container ends."""
        self._echo = threading.Thread(
            target=self._follow, args=(OutputEcho(sink),), daemon=True, name="policy-output"
        )
        self._echo.start()

    def _follow(self, echo: OutputEcho) -> None:
        # A client of its own without a read timeout (the SDK passes None on to requests, its
        # stubs say int): a policy may print nothing for longer than any request may take.
        url = self._engine_url
        client = DockerClient(base_url=url, version=_api_versions.get(url), timeout=None)  # type: ignore[arg-type]
        try:
            container = client.containers.get(self.name)
            for chunk in container.logs(stdout=True, stderr=True, stream=True, follow=True):
                echo.feed(chunk)
        except Exception as exc:  # the engine's, requests' or urllib3's: the stream broke off
            echo.feed(f"\n[the policy's output could not be followed: {exc}]\n".encode())
        finally:
            echo.close()
            client.close()

    def stop(self) -> None:
        """Give the policy a moment to exit, keep its log tail, then kill and remove it."""
        if self._stopped:
            return
        self._stopped = True
        deadline = time.monotonic() + STOP_GRACE_S
        state = self._ended(max_age=0)
        while state is None and time.monotonic() < deadline:
            time.sleep(0.05)
            state = self._ended(max_age=0)
        if state is not None:
            code, oom_killed = int(state.get("ExitCode", 0)), bool(state.get("OOMKilled"))
            self._detail = exit_detail(
                exit_code=code, oom_killed=oom_killed, memory_mib=self._limits.memory_mib
            )
            if memory_killed(exit_code=code, oom_killed=oom_killed):
                self._breach = memory_breach(ENGINE, self._limits.memory_mib)
        elif self._processes() >= self._limits.pids:
            self._breach = process_breach(ENGINE, self._limits.pids)
        self._tail = self._read_logs()
        _remove(self._container)
        if self._echo is not None:
            self._echo.join(STOP_GRACE_S)  # the stream ends with the container
        with self._lock:
            if self._state is None:
                self._state = {}  # killed by us: no exit of the policy's own
        self._client.close()

    def _processes(self) -> int:
        """How many processes the running container holds now (0 if it cannot be told)."""
        try:
            stats = cast(dict[str, Any], self._container.stats(stream=False))
        except DockerException as exc:
            log.warning("cannot read %s's process count: %s", self.name, exc)
            return 0
        return int((stats.get("pids_stats") or {}).get("current") or 0)

    def _ended(self, *, max_age: float) -> dict[str, Any] | None:
        # Inspecting, not the engine's blocking wait: Podman 4 busy-polls for every waiter.
        with self._lock:
            if self._state is not None or time.monotonic() - self._polled < max_age:
                return self._state
            self._polled = time.monotonic()
            try:
                self._container.reload()
            except NotFound:
                self._state = {}  # removed behind our back: not running, exit unknown
            except DockerException:
                pass  # the engine hiccuped: ask again later
            else:
                state = self._container.attrs.get("State", {})
                self._state = None if state.get("Running", False) else state
            return self._state

    def _read_logs(self) -> str:
        try:
            data: bytes = self._container.logs(stdout=True, stderr=True)
        except DockerException as exc:
            return f"[the policy's output could not be read: {exc}]"
        if len(data) <= LOG_TAIL_BYTES:
            return data.decode("utf-8", errors="replace")
        dropped = len(data) - LOG_TAIL_BYTES
        text = data[-LOG_TAIL_BYTES:].decode("utf-8", errors="replace")
        return f"[... {dropped} earlier bytes dropped]\n{text}"


def _remove(container: Container) -> None:
    try:
        container.remove(force=True, v=True)
    except NotFound:
        pass
    except DockerException:
        # The reconciler removes it later by its labels.
        log.exception("could not remove policy container %s", container.name)


def remove_leftovers(
    client: DockerClient, *, service: str, keep: set[str], grace_s: float = 60.0
) -> list[str]:
    """Remove the policy containers of `service`'s attempts not in `keep` (see `attempt_key`);
    their names.

    Containers younger than `grace_s` are spared: their attempt may have started after the
    caller read which attempts are live.
    """
    removed = []
    now = time.time()
    ours = [f"{LABEL_ROLE}={ROLE_POLICY}", f"{LABEL_SERVICE}={service}"]
    for container in client.containers.list(all=True, filters={"label": ours}):
        labels = container.labels
        key = attempt_key(labels.get(LABEL_SUBMISSION, "?"), labels.get(LABEL_ATTEMPT, "?"))
        if key in keep or now - _created(labels) < grace_s:
            continue
        _remove(container)
        removed.append(str(container.name))
    return removed


def _created(labels: Mapping[str, str]) -> float:
    try:
        return float(labels.get(LABEL_CREATED, ""))
    except ValueError:
        return 0.0  # not ours to date: old enough
