"""A private PostgreSQL instance for one test, which it may stop and start at will (the
machine's shared one on 5432 is never touched). `initdb` refuses to run as root, so as root
the cluster belongs to the `postgres` system user."""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from tests.worker.redis_server import free_port


def missing(message: str) -> None:
    """A part this test needs cannot run here: skipped, but a failure in CI (`CI=true`)."""
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)


class PrivatePostgres:
    """`initdb` once, then `start()`/`stop()` as often as a test likes; `remove()` at the end."""

    def __init__(self) -> None:
        if shutil.which("initdb") is None or shutil.which("pg_ctl") is None:
            missing("initdb/pg_ctl are not installed (apt-get install postgresql)")
        self._as: list[str] = []
        # Not under pytest's tmp_path: as root that is 0700 and the postgres user cannot enter.
        self.work = Path(tempfile.mkdtemp(prefix="manieval-pg-"))
        if os.geteuid() == 0:
            try:
                owner = pwd.getpwnam("postgres")
            except KeyError:
                missing("as root, initdb needs a `postgres` system user")
            os.chown(self.work, owner.pw_uid, owner.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"]
        self.port = free_port()
        self.data = self.work / "data"
        self.url = f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"
        self._run("initdb", "-D", str(self.data), "-U", "postgres", "--auth=trust", "-N")

    def _run(self, *args: str) -> None:
        result = subprocess.run(
            [*self._as, *args], capture_output=True, text=True, timeout=300, check=False
        )
        if result.returncode != 0:
            raise RuntimeError(f"{args[0]} failed: {result.stdout}\n{result.stderr}")

    def start(self) -> None:
        options = f"-p {self.port} -k {self.work} -c listen_addresses=127.0.0.1 -c fsync=off"
        self._run(
            "pg_ctl", "-D", str(self.data), "-o", options, "-l", str(self.work / "log"), "-w",
            "-t", "300", "start",
        )  # fmt: skip

    def stop(self) -> None:
        """A fast shutdown: open connections are cut, as in a real database restart."""
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "300", "stop")

    def remove(self) -> None:
        if (self.data / "postmaster.pid").exists():
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(self.work, ignore_errors=True)
