"""worker/run.py: an evaluation's progress goes to the server from the heartbeat's thread, so
a server that does not answer (a worker cut off from it) never holds the episodes up; the
evaluator runs in the worker, whatever evaluator image the challenge names."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from evaluator import evaluation
from evaluator.results import EpisodeResult, EvaluationResult
from evaluator.sources import LocalDirectory
from internal_api.schemas import ReportOut, State
from server.models import Submission
from server.submissions.service import Resolved, submit
from testkit.factories import make_challenge, make_user
from testkit.waiting import until
from tests.evaluator.conftest import SCRIPTED, tiny_plan
from worker import run
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

pytestmark = pytest.mark.sim


class SilentServer:
    """A server whose answers to progress hang until `answer` is set (a cut link)."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.answer = threading.Event()
        self.sent: list[dict[str, Any]] = []

    def progress(self, _sid: int, _attempt: int, progress: dict[str, Any]) -> ReportOut:
        assert self.answer.wait(600), "the test never let the server answer"
        self.sent.append(progress)
        return ReportOut(applied=True, state=State.RUNNING)


def test_episodes_go_on_while_the_server_does_not_answer_their_progress(
    monkeypatch: pytest.MonkeyPatch,
):
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=3)
    ran: list[EpisodeResult] = []
    real = evaluation.evaluate

    def counting(*args: Any, **kwargs: Any) -> EvaluationResult:
        told = kwargs["on_episode"]

        def on_episode(run_index: int, episode: EpisodeResult) -> None:
            told(run_index, episode)  # the worker's report: it must not wait on the server
            ran.append(episode)

        return real(*args, **{**kwargs, "on_episode": on_episode})

    monkeypatch.setattr(evaluation, "evaluate", counting)
    server = SilentServer()
    outcome: list[object] = []
    evaluating = threading.Thread(
        target=lambda: outcome.append(
            run._evaluate(server, 1, 1, plan, LocalDirectory(SCRIPTED), processes=0)  # type: ignore[arg-type]
        )
    )
    evaluating.start()
    try:
        until(
            lambda: len(ran) == plan.episode_count(),
            "every episode, the server silent",
            timeout=600,
        )
    finally:
        server.answer.set()  # the link is back
        evaluating.join(600)
    (result,) = outcome
    assert isinstance(result, EvaluationResult)
    assert server.sent[-1]["done"] == plan.episode_count()  # the last word reached it


def test_the_docker_executor_evaluates_in_the_worker_and_ignores_the_challenges_image(
    committed_sessions: sessionmaker[Session], api: ServerAPI, wsettings: WorkerSettings
):
    """The evaluator runs in the worker's own environment there: a challenge's evaluator image
    (for its Kubernetes Jobs) is neither run nor refused, whatever the worker lists."""
    image = "127.0.0.1:5000/lab/evaluator-lab-tasks@sha256:" + "1a" * 32
    with committed_sessions() as db:
        challenge = make_challenge(db, evaluator_image=image)
        submission = submit(
            db,
            user=make_user(db, "alice"),
            challenge=challenge,
            phase=next(p for p in challenge.phases if p.name == "dev"),
            image="local:scripted",
            description="",
            public=True,
            resolve=lambda _image: Resolved(pinned="local:scripted", size_bytes=None),
        )
        db.commit()
    assert wsettings.executor == "docker"
    assert image not in wsettings.allowed_evaluator_images
    assert run.run_next(api, wsettings) == (submission.id, State.SUCCEEDED)
    with committed_sessions() as db:
        done = db.get(Submission, submission.id)
        assert done is not None
        result = EvaluationResult.model_validate(done.result)
    assert result.provenance is not None
    assert result.provenance.evaluator.image is None  # no image ran it
