"""The embedded default's registry and engine: supervised children (restarted when they die,
stopped with the service), and a server that still starts, and says why, without them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from manieval import policy_base as policy_base_module
from manieval.engines import Engines, EngineSettings
from manieval.supervise import Supervised
from server.kit.settings import Settings
from server.registry.published import LOCAL_POLICY_BASE, POLICY_BASE_REPOSITORY, policy_base
from server.registry.service import server_pull_token
from testkit.factories import PASSWORD
from tests.cli.conftest import free_port, running_server
from tests.cli.push_support import build_base_image
from tests.server.registry_fixture import require_tool


def _http_server(tmp_path: Path) -> tuple[Supervised, int]:
    port = free_port()
    child = Supervised(
        "web",
        [sys.executable, "-m", "http.server", "--bind", "127.0.0.1", str(port)],
        ready=lambda: urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2).status == 200,
        cwd=tmp_path,
        log_path=tmp_path / "web.log",
        pid_path=tmp_path / "web.pid",
    )
    return child, port


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return Path(f"/proc/{pid}/status").read_text().find("State:\tZ") >= 0


def _wait(condition: Callable[[], bool], timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if condition():
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise AssertionError("timed out")


def test_a_supervised_child_is_restarted_when_it_dies_and_stopped_with_us(tmp_path: Path) -> None:
    child, _port = _http_server(tmp_path)
    assert child.start(), child.problem
    first = child.pid
    assert first is not None
    try:
        os.kill(first, signal.SIGKILL)
        _wait(lambda: child.pid != first and child.problem is None)
        assert child.restarts == 1
    finally:
        child.stop()
    assert child.pid is None
    assert _gone(first)
    assert not (tmp_path / "web.pid").exists()


def test_a_child_left_by_a_killed_run_is_ended_at_the_next_start(tmp_path: Path) -> None:
    child, _port = _http_server(tmp_path)
    # What a `kill -9` of the service leaves: the child running, its PID file in the data dir.
    left = subprocess.Popen(child.argv, cwd=tmp_path, start_new_session=True)
    (tmp_path / "web.pid").write_text(f"{left.pid}\n")
    try:
        _wait(child.ready)
        assert child.start(), child.problem  # the port was freed: the leftover was ended
        assert child.pid != left.pid
        assert left.wait(timeout=30) is not None
    finally:
        child.stop()
        if left.poll() is None:
            left.kill()
            left.wait()


def test_a_pid_file_naming_another_program_is_left_alone(tmp_path: Path) -> None:
    child, _port = _http_server(tmp_path)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    (tmp_path / "web.pid").write_text(f"{other.pid}\n")
    try:
        assert child.start(), child.problem
        assert other.poll() is None  # not ours: never signalled
    finally:
        child.stop()
        other.kill()
        other.wait()


def test_what_is_missing_is_said_once_and_images_are_refused(tmp_path: Path) -> None:
    settings = Settings(dev_mode=True, data_dir=tmp_path)
    empty = tmp_path / "bin"
    empty.mkdir()
    os.environ["PATH"], saved = str(empty), os.environ["PATH"]
    try:
        engines = Engines(settings, server_url="http://127.0.0.1:1", options=EngineSettings())
    finally:
        os.environ["PATH"] = saved
    assert engines.missing == ["docker-registry", "podman"]
    assert engines.missing_line() == (
        "docker-registry and podman not installed: policy images cannot be submitted or run "
        "(bundled examples still can); install with: apt-get install -y podman docker-registry"
    )
    assert engines.refusal() is not None
    assert "apt-get install -y podman docker-registry" in str(engines.refusal())
    assert engines.start() == []
    assert engines.server_settings() == settings  # no registry to announce


def test_serve_without_the_tools_starts_and_refuses_images_with_the_reason(
    tmp_path: Path,
) -> None:
    empty = tmp_path / "bin"
    empty.mkdir()
    extra = {
        "MANIEVAL_EMBEDDED_REGISTRY": "true",
        "MANIEVAL_EMBEDDED_ENGINE": "true",
        "PATH": str(empty),
    }
    with running_server(tmp_path / "data", extra=extra) as server:
        lines = [line for line in server.log.read_text().splitlines() if "not installed" in line]
        assert len(lines) == 1, lines
        assert "apt-get install -y podman docker-registry" in lines[0]
        with httpx.Client(base_url=server.url, timeout=30) as http:
            http.post(
                "/api/v1/users",
                json={"username": "alice", "email": "a@example.org", "password": PASSWORD},
            )
            token = http.post(
                "/api/v1/auth/token",
                json={"login": "alice", "password": PASSWORD, "name": "t"},
            ).json()["token"]
            r = http.post(
                "/api/v1/submissions",
                json={"challenge": "server-tiny", "image": "127.0.0.1:5000/alice/p:v1"},
                headers={"Authorization": f"Bearer {token}"},
            )
        assert r.status_code == 503, r.text
        assert "podman" in json.dumps(r.json())
        assert "apt-get install" in r.json()["error"]["message"]


def test_serve_starts_and_stops_the_registry_and_podman(tmp_path: Path) -> None:
    require_tool("docker-registry")
    require_tool("podman")
    registry = f"127.0.0.1:{free_port()}"
    extra = {
        "MANIEVAL_EMBEDDED_REGISTRY": "true",
        "MANIEVAL_EMBEDDED_ENGINE": "true",
        "MANIEVAL_EMBEDDED_REGISTRY_ADDR": registry,
    }
    data = tmp_path / "data"
    with running_server(data, extra=extra) as server:
        assert f"registry: {registry}" in server.log.read_text()
        # token auth is on: anonymous access is refused, and it names this server's realm
        r = httpx.get(f"http://{registry}/v2/", timeout=10)
        assert r.status_code == 401
        assert f'realm="{server.url}/registry/token"' in r.headers["www-authenticate"]
        socket = data / "engine" / "podman.sock"
        transport = httpx.HTTPTransport(uds=str(socket))
        with httpx.Client(transport=transport, timeout=10) as engine:
            assert engine.get("http://engine/_ping").status_code == 200
        pids = [
            int((data / d / f"{n}.pid").read_text())
            for d, n in (("registry", "registry"), ("engine", "podman"))
        ]
        assert (data / "registry" / "storage").is_dir()
    for pid in pids:
        _wait(lambda pid=pid: _gone(pid), timeout=30)


def test_the_policy_base_is_published_in_the_registry_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The engine's base goes into the embedded registry at start, for participants to build on
    without a checkout; while the registry has that very image, nothing is copied again; an
    engine without one is said in a line."""
    skopeo = require_tool("skopeo")
    build_base_image()
    settings = Settings(dev_mode=True, data_dir=tmp_path)
    options = EngineSettings(embedded_registry_addr=f"127.0.0.1:{free_port()}")
    engines = Engines(settings, server_url="http://127.0.0.1:1", options=options)
    try:
        assert engines.start() == []
        domain = engines.registry_domain
        assert domain is not None
        token = server_pull_token(settings, repository=POLICY_BASE_REPOSITORY)
        inspected = subprocess.run(
            [
                *(skopeo, "inspect", "--raw", "--tls-verify=false", "--registry-token", token),
                f"docker://{policy_base(domain)}",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert inspected.returncode == 0, inspected.stderr
        local = subprocess.run(
            ["podman", "image", "inspect", "--format", "{{.Id}}", LOCAL_POLICY_BASE],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert json.loads(inspected.stdout)["config"]["digest"] == f"sha256:{local.stdout.strip()}"

        ran: list[str] = []
        run = subprocess.run

        def recorded(args: list[str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
            ran.append(args[1])
            return run(args, **kwargs)

        monkeypatch.setattr(subprocess, "run", recorded)  # the engines module's too
        assert engines.publish_policy_base() is None
        assert ran == ["inspect"]  # the registry has it already

        monkeypatch.setattr(policy_base_module, "LOCAL_POLICY_BASE", "localhost/manieval-none:x")
        said = engines.publish_policy_base()
        assert said is not None
        assert "the engine has no localhost/manieval-none:x" in said
        assert "the template's base/Dockerfile" in said
    finally:
        engines.stop()


def test_the_copy_reads_the_engine_and_writes_with_the_servers_token() -> None:
    target = "docker://127.0.0.1:5000/manieval/policy-base:bookworm"
    args = policy_base_module.copy_args(
        "/usr/bin/skopeo", engine_url="unix:///d/engine/podman.sock", target=target, token="T"
    )
    assert args[:2] == ["/usr/bin/skopeo", "copy"]
    assert args[args.index("--src-daemon-host") + 1] == "unix:///d/engine/podman.sock"
    assert args[args.index("--dest-registry-token") + 1] == "T"
    assert "--dest-tls-verify=false" in args  # the embedded registry: plain HTTP on loopback
    assert args[-2:] == [f"docker-daemon:{LOCAL_POLICY_BASE}", target]
    inspect = policy_base_module.inspect_args("skopeo", target=target, token="T")
    assert inspect == [
        *("skopeo", "inspect", "--raw", "--tls-verify=false", "--registry-token", "T", target)
    ]
