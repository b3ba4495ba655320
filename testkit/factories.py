"""Plain helpers for tests of the server, the web pages, the worker and the CLI: users,
challenges, submissions and result documents through the real code paths, a queue that records,
a registry stand-in, and API tokens."""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from evaluator.provenance import environment
from evaluator.results import (
    Abort,
    ConditionResult,
    EpisodeResult,
    EvaluationResult,
    EvaluatorBuild,
    Machine,
    Provenance,
    ScoringSettings,
    SuiteRef,
    Versions,
    aggregate_task,
)
from evaluator.runner import failed_episode
from evaluator.suite import load_suite
from server.accounts import service as accounts
from server.challenges.service import ChallengeOptions, load_challenge
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.image_refs import ImageReference, ResolvedImage
from server.kit.settings import Settings
from server.models import Challenge, Submission, User
from server.submissions.images import image_resolver
from server.submissions.service import Resolved, Resolver, submit

SUITE = Path(__file__).resolve().parent / "server_suite.yaml"
PASSWORD = "correct horse battery staple"


def make_user(db: Session, username: str, *, admin: bool = False, verified: bool = True) -> User:
    """A user with the test password; its address verified unless `verified` is False."""
    user = accounts.register(
        db, username=username, email=f"{username}@example.org", password=PASSWORD, admin=admin
    )
    if verified:
        user.email_verified_at = datetime.now(UTC)
    db.commit()
    return user


def make_challenge(db: Session, **options: object) -> Challenge:
    challenge = load_challenge(
        db,
        SUITE,
        ChallengeOptions(**options),
        seed_secret="s" * 32,  # type: ignore[arg-type]
    )
    db.commit()
    return challenge


def embedded_database(settings: Settings, **options: object) -> sessionmaker[Session]:
    """A migrated database for `settings` with two challenges: `server-tiny`, and
    `server-long` (200 episodes of 100 steps: long enough to cancel or kill a run mid-way)."""
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    long_suite = settings.data_dir / "server-long.yaml"
    long_suite.write_text(
        SUITE.read_text()
        .replace("name: server-tiny", "name: server-long")
        .replace("max_episode_steps: 12, episodes: 2", "max_episode_steps: 100, episodes: 200")
    )
    with sessions.begin() as db:
        for suite in (SUITE, long_suite):
            load_challenge(
                db,
                suite,
                ChallengeOptions(**options),  # type: ignore[arg-type]
                seed_secret=settings.secret("seed_secret"),
            )
    return sessions


def queue_submission(
    db: Session, user: User, challenge: Challenge, phase: str = "dev", *, policy_gpus: int = 0
) -> Submission:
    """A queued submission through the real submit path, with a stand-in pinned image (on a
    service with `policy_gpus` GPUs for a policy)."""
    target = next(p for p in challenge.phases if p.name == phase)
    return submit(
        db,
        user=user,
        challenge=challenge,
        phase=target,
        image="x",
        description="",
        public=True,
        resolve=lambda _image: Resolved(pinned="x@sha256:" + "0" * 64, size_bytes=1),
        policy_gpus=policy_gpus,
    )


def gpu_suite(directory: Path, *, gpus: int = 1) -> Path:
    """The server test suite as `server-gpu`, giving each policy `gpus` GPUs."""
    path = directory / "server-gpu.yaml"
    text = SUITE.read_text().replace("name: server-tiny", "name: server-gpu")
    path.write_text(text + f"policy: {{gpus: {gpus}}}\n")
    return path


def tiny_provenance(**environment_changes: str) -> Provenance:
    """The provenance of a server-tiny result evaluated in the environment this installation
    evaluates the suite in now, but for `environment_changes`."""
    suite = load_suite(SUITE)
    now = environment(suite_sha256=suite.sha256(), sim_backends=["physx_cpu"])
    return Provenance(
        environment=now.model_copy(update=environment_changes),
        suite_version=suite.version,
        evaluator=EvaluatorBuild(manieval="0.1.0", commit="f" * 40),
        policy_image="x@sha256:" + "0" * 64,
        machines=[Machine(cpu="AMD EPYC 7B13", gpu=None)],
        settings=ScoringSettings(
            ignore_terminations=False,
            control_mode={"PickCube-v1": "pd_ee_delta_pose"},
            max_episode_steps={"PickCube-v1": 12},
            action_chunk_max=1,
            action_chunk_execute=1,
        ),
    )


def result_doc(
    successes: list[bool],
    *,
    phase: str = "dev",
    conditions: tuple[str, ...] = ("nominal",),
    planned: int | None = None,
    abort: Abort | None = None,
    provenance: Provenance | None = None,
    recorded: bool = True,
) -> EvaluationResult:
    """A result of PickCube-v1 on the server-tiny suite: these episode outcomes, the same task
    under every condition; with `planned` more than ran, the rest `not_run` as the evaluator
    records them (aborted with `abort`, or completed as a cancelled evaluation is). Its
    provenance is `provenance`, by default `tiny_provenance()`; none unless `recorded`."""
    episodes = [
        EpisodeResult(
            index=i,
            seed=1000 + i,
            success_once=ok,
            success_at_end=ok,
            steps=10,
            episode_return=1.0,
            wall_time_s=0.1,
        )
        for i, ok in enumerate(successes)
    ]
    planned = len(episodes) if planned is None else planned
    episodes += [
        failed_episode(
            i, 1000 + i, "not_run", "the evaluation stopped before it", at_end_measured=True
        )
        for i in range(len(episodes), planned)
    ]
    task = aggregate_task("PickCube-v1", len(episodes), episodes)
    now = datetime.now(UTC)
    return EvaluationResult(
        suite=SuiteRef(name="server-tiny", version=1, sha256=load_suite(SUITE).sha256()),
        phase=phase,
        policy="test",
        versions=Versions(manieval="0", mani_skill="0", sapien="0", torch="0", python="3"),
        provenance=(provenance or tiny_provenance()) if recorded else None,
        started_at=now,
        finished_at=now,
        status="aborted" if abort else "completed",
        abort=abort,
        score=task.success_rate,
        conditions=[
            ConditionResult(name=name, params={"kind": name}, score=task.success_rate, tasks=[task])
            for name in conditions
        ],
    )


@dataclass
class RecordingQueue:
    sent: list[tuple[int, int]] = field(default_factory=list)

    def enqueue(self, submission_id: int, attempt: int) -> None:
        self.sent.append((submission_id, attempt))


class FakeRegistry:
    """Stands in for the registry where a test is not about it (the real one is tested in
    test_images.py and test_submit_registry.py); reference parsing is the real one."""

    def resolve(self, ref: ImageReference, *, max_bytes: int) -> ResolvedImage:
        digest = "sha256:" + uuid.uuid5(uuid.NAMESPACE_URL, str(ref)).hex * 2
        return ResolvedImage(
            reference=ref, digest=digest, size_bytes=1234, pinned=ref.pinned(digest)
        )


def fake_resolve_for(settings: Settings) -> Resolver:
    return image_resolver(settings, FakeRegistry())


def token_for(client: TestClient, username: str) -> dict[str, str]:
    """Log in by password and return Authorization headers with a fresh API token."""
    r = client.post("/api/v1/auth/token", json={"login": username, "password": PASSWORD})
    assert r.status_code == 201, r.text
    return {"Authorization": f"Bearer {r.json()['token']}"}
