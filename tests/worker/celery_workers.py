"""Real `celery worker` processes for the worker tests (tests/worker/test_celery.py,
test_outages.py and test_partition.py): their environment, checked to hold no database URL or
server secret, how they start, and a challenge added to the server they report to."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.settings import Settings
from testkit.factories import SUITE

REPO = Path(__file__).resolve().parents[2]
WORKER_START_S = 180.0  # a loaded 2-core machine imports torch and ManiSkill slowly
# What a worker's environment may hold: the broker, the server's URL and the worker token,
# its queue and data directory, and whether it runs the bundled `local:` policies.
WORKER_KEYS = {
    "MANIEVAL_SERVER_URL",
    "MANIEVAL_WORKER_TOKEN",
    "MANIEVAL_BROKER_URL",
    "MANIEVAL_CELERY_QUEUE",
    "MANIEVAL_ALLOW_LOCAL_POLICIES",
    "MANIEVAL_DATA_DIR",
}
OPTIONAL_KEYS = {  # names and patience, not secrets
    "MANIEVAL_WORKER_NAME",
    "MANIEVAL_RECONCILE_QUEUE",
    "MANIEVAL_REPORT_PATIENCE_S",
    "MANIEVAL_REQUEST_TIMEOUT_S",
    "MANIEVAL_SPOOL_RETRY_S",
}
SECRETS = {"MANIEVAL_DATABASE_URL", "MANIEVAL_SECRET_KEY", "MANIEVAL_SEED_SECRET"}

# The worker process with its `local:` policies in the given directory, then `celery ARGS`.
LAUNCHER = (
    "import sys, pathlib, evaluator.bundled\n"
    "evaluator.bundled.EXAMPLES_DIR = pathlib.Path(sys.argv[1])\n"
    "sys.argv = ['celery', *sys.argv[2:]]\n"
    "from celery.__main__ import main\n"
    "main()\n"
)


def celery_server_settings(
    work: Path, *, database_url: str, broker_url: str, queue: str, **extra: object
) -> Settings:
    """A server's settings for tests with real Celery workers: a private database and broker,
    its own queue, the bundled `local:` policies, and rates no test reaches."""
    return Settings(
        dev_mode=True,
        data_dir=work / "server",
        database_url=database_url,
        queue="celery",
        broker_url=broker_url,
        celery_queue=queue,
        allow_local_policies=True,
        cookie_secure=False,
        submit_rate="1000/minute",
        **extra,  # type: ignore[arg-type]
    )


def add_challenge(settings: Settings, name: str, **replace: str) -> None:
    """Another challenge of the server test suite, named `name`, with text replaced."""
    suite = settings.data_dir / f"{name}.yaml"
    source = SUITE.read_text().replace("name: server-tiny", f"name: {name}")
    for old, new in replace.items():
        assert old in source, old
        source = source.replace(old, new)
    suite.write_text(source)
    load_suite_file(settings, suite)


def load_suite_file(settings: Settings, suite: Path) -> None:
    """Load a suite file as a challenge of the server's database, as `challenge load` does."""
    from server.kit.db import make_engine, session_factory

    engine = make_engine(settings.resolved_database_url)
    try:
        with session_factory(engine).begin() as db:
            load_challenge(
                db,
                suite,
                ChallengeOptions(quota_concurrent=50, quota_per_day=1000),
                seed_secret=settings.secret("seed_secret"),
            )
    finally:
        engine.dispose()


def worker_environment(
    settings: Settings, *, server_url: str, data_dir: Path, **extra: str
) -> dict[str, str]:
    """A worker's whole environment: this process's, without any MANIEVAL_* setting, plus
    the broker, the server's URL and the worker token. No database URL, no server secret."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MANIEVAL_")}
    env |= {
        "MANIEVAL_SERVER_URL": server_url,
        "MANIEVAL_WORKER_TOKEN": settings.secret("worker_token"),
        "MANIEVAL_BROKER_URL": settings.broker_url,
        "MANIEVAL_CELERY_QUEUE": settings.celery_queue,
        "MANIEVAL_ALLOW_LOCAL_POLICIES": "true",
        "MANIEVAL_DATA_DIR": str(data_dir),
        "PYTHONUNBUFFERED": "1",
    }
    env |= extra
    keys = {k for k in env if k.startswith("MANIEVAL_")}
    assert WORKER_KEYS <= keys <= WORKER_KEYS | OPTIONAL_KEYS, keys
    assert not keys & SECRETS
    assert settings.secret("secret_key") not in env.values()
    assert settings.secret("seed_secret") not in env.values()
    return env


def celery_worker(
    env: dict[str, str],
    *,
    queues: str,
    policies: Path,
    log: Path,
    prefix: Sequence[str] = (),
) -> subprocess.Popen[bytes]:
    """`celery worker` in its own process group (killed as a whole), one task at a time;
    `prefix` runs it through another command (`ip netns exec NS`, which execs it in place)."""
    with log.open("ab") as out:
        return subprocess.Popen(
            [*prefix, sys.executable, "-c", LAUNCHER, str(policies),
             "-A", "worker.celery_app", "worker", "--pool", "solo", "--concurrency", "1",
             "--without-gossip", "--without-mingle", "--without-heartbeat",
             "--loglevel", "INFO", "-Q", queues],
            env=env, cwd=REPO, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip


def wait_ready(process: subprocess.Popen[bytes], log: Path) -> None:
    """Until the worker said it is ready (consuming its queue)."""
    deadline = time.monotonic() + WORKER_START_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"the worker exited ({process.returncode}):\n{log.read_text()}")
        if "ready." in log.read_text(errors="replace"):
            return
        time.sleep(0.2)
    raise AssertionError(f"the worker did not start in {WORKER_START_S} s:\n{log.read_text()}")
