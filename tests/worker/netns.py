"""A private network for one test: hosts in network namespaces, joined by veth pairs to a
bridge in this one, whose links the test cuts and heals (tests/worker/test_partition.py).

The bridge holds the address of this namespace's side (the server, its Redis), each host
namespace one address of the same /24 and its loopback. Everything is named per run (the
pid and a random suffix) and removed by `remove()`, which the fixture calls however the test
ends. The /24 is drawn from 10.0.0.0/8 among prefixes no route of this machine names, so no
traffic leaves for any address the test did not make. Needs root and iproute2; where a
namespace cannot be made the test is skipped (a failure with `CI=true`).
"""

from __future__ import annotations

import ipaddress
import os
import random
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from tests.private_postgres import missing

RTO_MAX = Path("/proc/sys/net/ipv4/tcp_rto_max_ms")
"""TCP's longest retransmission wait (120 s by default): after a cut of a few seconds a
connection's next try may come that much later than the heal. Set per namespace where the
kernel has it; without it the waits after a heal are longer, not different."""


def ip(*args: str) -> str:
    """`ip ARGS`; raises with its message when it fails."""
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")
    return done.stdout


@dataclass(frozen=True)
class Host:
    name: str
    namespace: str
    link: str
    """Its veth pair's end on the bridge, in this namespace: down is a cut cable."""
    address: str

    @property
    def exec(self) -> list[str]:
        """The command prefix that runs a program inside the host's namespace."""
        return ["ip", "netns", "exec", self.namespace]


@dataclass
class Network:
    tag: str
    subnet: ipaddress.IPv4Network
    bridge: str
    hosts: dict[str, Host] = field(default_factory=dict)

    @property
    def address(self) -> str:
        """This namespace's address on the bridge (what the hosts reach)."""
        return str(self.subnet.network_address + 1)

    def cut(self, host: Host) -> None:
        ip("link", "set", host.link, "down")

    def heal(self, host: Host) -> None:
        ip("link", "set", host.link, "up")

    def add_host(self, name: str) -> Host:
        host = Host(
            name=name,
            namespace=f"manieval-{self.tag}-{name}",
            link=f"mv{self.tag}{name}"[:15],
            address=str(self.subnet.network_address + 2 + len(self.hosts)),
        )
        self.hosts[name] = host
        ip("netns", "add", host.namespace)
        ip(
            "link",
            "add",
            host.link,
            "type",
            "veth",
            "peer",
            "name",
            "eth0",
            "netns",
            host.namespace,
        )
        ip("link", "set", host.link, "master", self.bridge)
        ip("link", "set", host.link, "up")
        inside = ("-n", host.namespace)
        ip(*inside, "addr", "add", f"{host.address}/{self.subnet.prefixlen}", "dev", "eth0")
        ip(*inside, "link", "set", "eth0", "up")
        ip(*inside, "link", "set", "lo", "up")
        if RTO_MAX.exists():  # Linux 6.15+: a healed link is used again within a second
            subprocess.run([*host.exec, "sh", "-c", f"echo 1000 > {RTO_MAX}"], check=True)
        return host

    def remove(self) -> None:
        """Delete every namespace, link and the bridge this network made (each at most once,
        whatever failed before)."""
        for host in self.hosts.values():
            for args in (("netns", "del", host.namespace), ("link", "del", host.link)):
                try:
                    ip(*args)
                except RuntimeError:
                    pass  # not made, or gone with its namespace (the veth pair dies whole)
        try:
            ip("link", "del", self.bridge)
        except RuntimeError:
            pass


def _unused_subnet() -> ipaddress.IPv4Network:
    routes = ip("-4", "route", "show", "table", "all") + ip("-4", "addr", "show")
    used = [
        ipaddress.ip_network(word, strict=False)
        for word in routes.split()
        if word[:1].isdigit() and word.count(".") == 3
    ]
    for _ in range(50):
        subnet = ipaddress.IPv4Network(
            f"10.{random.randint(64, 254)}.{random.randint(0, 255)}.0/24"
        )
        if not any(subnet.overlaps(u) for u in used if u.prefixlen > 0):
            return subnet
    raise RuntimeError("no unused 10.x.y.0/24 for the test's network")


def make_network(*hosts: str) -> Network:
    """The bridge with this namespace's address and the named hosts; skipped (failed in CI)
    where they cannot be made."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        missing("network namespaces need root and iproute2 (`ip`; apt-get install iproute2)")
    tag = f"{os.getpid() % 100000:05d}{random.randrange(16**3):03x}"
    network: Network | None = None
    try:
        network = Network(tag=tag, subnet=_unused_subnet(), bridge=f"mvbr{tag}")
        ip("link", "add", network.bridge, "type", "bridge")
        ip("addr", "add", f"{network.address}/{network.subnet.prefixlen}", "dev", network.bridge)
        ip("link", "set", network.bridge, "up")
        for name in hosts:
            network.add_host(name)
        return network
    except RuntimeError as exc:
        if network is not None:
            network.remove()
        missing(f"cannot make a bridge or network namespace here: {exc}")
        raise  # unreachable: missing() skips or fails
