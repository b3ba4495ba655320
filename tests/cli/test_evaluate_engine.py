"""Which container engine `manieval evaluate --image` uses when none is named: the local demo's
(in its data directory) while it runs, else the system's; and an error that says where it
looked and how to name one."""

from __future__ import annotations

import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from evaluator.sources import PolicySourceError
from manieval.engines import default_engine, engine_socket
from manieval.evaluate import _source
from worker.containers import DEFAULT_ENGINE_URL


@pytest.fixture
def data_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A data directory with a short path (a unix socket's path holds at most 107 bytes),
    named to the CLI as a demo's is: MANIEVAL_DATA_DIR."""
    with tempfile.TemporaryDirectory(prefix="mev") as directory:
        monkeypatch.setenv("MANIEVAL_DATA_DIR", directory)
        monkeypatch.delenv("MANIEVAL_DOCKER_ENGINE_URL", raising=False)
        yield Path(directory)


def bound_socket(path: Path) -> socket.socket:
    """A socket file at `path` that no engine answers on (bound, not listening)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(path))
    return sock


def test_without_a_local_engine_the_system_engine_is_the_default(data_dir: Path) -> None:
    url, looked = default_engine(data_dir, DEFAULT_ENGINE_URL)
    assert url == DEFAULT_ENGINE_URL
    assert looked == [f"unix://{data_dir}/engine/podman.sock", DEFAULT_ENGINE_URL]


def test_the_local_demos_engine_is_the_default_while_its_socket_exists(data_dir: Path) -> None:
    with bound_socket(engine_socket(data_dir)):
        url, _ = default_engine(data_dir, DEFAULT_ENGINE_URL)
    assert url == f"unix://{data_dir}/engine/podman.sock"


def test_an_unusable_default_engine_says_where_it_looked_and_how_to_name_one(
    data_dir: Path,
) -> None:
    local = engine_socket(data_dir)
    with bound_socket(local), pytest.raises(PolicySourceError) as raised:
        _source(None, "localhost/policy:v1", None)
    message = str(raised.value)
    assert message.startswith(f"cannot use the container engine at unix://{local} ")
    assert f"(looked for an engine at unix://{local} then {DEFAULT_ENGINE_URL})" in message
    assert "--engine unix:///PATH/podman.sock" in message
    assert "MANIEVAL_DATA_DIR" in message


def test_a_named_engine_is_used_as_named(data_dir: Path) -> None:
    named = data_dir / "mine.sock"
    with bound_socket(named), pytest.raises(PolicySourceError) as raised:
        _source(None, "localhost/policy:v1", f"unix://{named}")
    assert str(raised.value).startswith(f"cannot use the container engine at unix://{named}: ")
