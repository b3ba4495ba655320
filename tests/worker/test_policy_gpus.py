"""A worker gives a policy's container the GPUs its suite asks for, or ends the attempt with
the reason when it has fewer than the server promised (its MANIEVAL_POLICY_GPUS)."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import State
from manieval.service import embedded_worker_settings
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.settings import Settings
from server.models import Submission
from testkit.factories import gpu_suite, make_user, queue_submission
from testkit.workers import worker_settings
from worker.containers import ContainerImage
from worker.run import policy_source, run_next
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

PINNED = "127.0.0.1:5000/alice/policy@sha256:" + "ab" * 32


def test_a_worker_without_the_gpus_ends_the_attempt_with_the_reason(
    api: ServerAPI,
    wsettings: WorkerSettings,
    committed_sessions: sessionmaker[Session],
    tmp_path: Path,
) -> None:
    assert wsettings.policy_gpus == 0
    with committed_sessions() as db:
        challenge = load_challenge(
            db, gpu_suite(tmp_path), ChallengeOptions(), seed_secret="s" * 32
        )
        # Accepted by a server told it has a GPU for policies: this worker has none.
        sid = queue_submission(db, make_user(db, "alice"), challenge, policy_gpus=1).id
        db.commit()
    assert run_next(api, wsettings) == (sid, State.ERROR)
    with committed_sessions() as db:
        submission = db.get(Submission, sid)
        assert submission is not None
        assert submission.reason == (
            "cannot run: this challenge asks for 1 GPU per policy, and this service has none "
            "for policies (its operator sets MANIEVAL_POLICY_GPUS)"
        )


def test_the_docker_executor_is_handed_the_suites_gpus(settings: Settings) -> None:
    wsettings = worker_settings(settings, docker_engine_url="unix:///nowhere.sock", policy_gpus=1)
    source = policy_source(PINNED, wsettings, submission_id=3, attempt=1, gpus=1)
    assert isinstance(source, ContainerImage)
    assert source.gpus == 1
    assert policy_source(PINNED, wsettings, submission_id=3, attempt=1).gpus == 0  # type: ignore[union-attr]


def test_the_embedded_worker_gives_what_its_server_promises(settings: Settings) -> None:
    promising = settings.model_copy(update={"policy_gpus": 1})
    assert embedded_worker_settings(promising, port=8000).policy_gpus == 1
    assert embedded_worker_settings(settings, port=8000).policy_gpus == 0
