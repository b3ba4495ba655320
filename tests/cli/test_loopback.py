"""Which addresses count as this machine: the one rule behind plain HTTP that is allowed
without a warning (a password at `manieval login`) or a flag (`--tls-verify=false` for a
registry). A name that only begins with ``127.`` is another machine, wherever it is checked."""

from __future__ import annotations

import pytest

from manieval.client import is_loopback, is_loopback_domain
from manieval.engine_login import Engine, login_command, tls_flags
from server.kit.settings import Settings
from server.registry.own import loopback_domain, plain_http

STRONG = "s" * 40
THIS_MACHINE = ["127.0.0.1:5000", "127.8.9.10:443", "localhost:5000", "LocalHost", "[::1]:5000"]
ANOTHER = ["127.evil.example:5000", "127.0.0.1.nip.io:5000", "10.0.0.1:5000", "[::2]:5000"]
ANOTHER += ["registry.example", "localhost.example:5000", "0.0.0.0:5000"]


@pytest.mark.parametrize("domain", THIS_MACHINE)
def test_loopback_names_and_addresses_are_this_machine_for_the_cli_and_the_server(
    domain: str,
) -> None:
    assert is_loopback(f"http://{domain}/")
    assert is_loopback_domain(domain)
    assert loopback_domain(domain)


@pytest.mark.parametrize("domain", ANOTHER)
def test_a_name_that_only_looks_local_is_another_machine(domain: str) -> None:
    assert not is_loopback(f"http://{domain}/")
    assert not is_loopback_domain(domain)
    assert not loopback_domain(domain)


def test_podman_skips_tls_only_for_a_registry_on_this_machine() -> None:
    podman, docker = Engine("podman", "/usr/bin/podman"), Engine("docker", "/usr/bin/docker")
    assert tls_flags(podman, "127.0.0.1:5000") == ["--tls-verify=false"]
    assert tls_flags(podman, "[::1]:5000") == ["--tls-verify=false"]
    assert tls_flags(podman, "127.evil.example:5000") == []
    assert tls_flags(docker, "127.0.0.1:5000") == []
    assert "--tls-verify=false" not in login_command("podman", "127.evil.example", "alice")
    assert "--tls-verify=false" in login_command("podman", "localhost:5000", "alice")


def test_the_server_speaks_plain_http_to_its_own_registry_only_on_loopback_or_when_told() -> None:
    settings = Settings(
        secret_key=STRONG,
        seed_secret=STRONG,
        worker_token=STRONG,
        insecure_registries=["registry.internal:5000"],
    )
    assert plain_http(settings, "127.0.0.1:5000")
    assert plain_http(settings, "registry.internal:5000")
    assert not plain_http(settings, "127.evil.example:5000")
    assert not plain_http(settings, "registry.example")
