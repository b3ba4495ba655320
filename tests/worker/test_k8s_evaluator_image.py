"""A challenge's own evaluator image on Kubernetes: the Job's evaluator runs on it when the
workers list it (`MANIEVAL_EVALUATOR_IMAGES`), else on `MANIEVAL_EVALUATOR_IMAGE`; a challenge
naming an image they do not list ends `error`, the configuration's doing.

The Job goes to the API-server double; what it would run is read from the manifest.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from pydantic import ValidationError
from sqlalchemy.orm import Session, sessionmaker

from evaluator.provenance import EVALUATOR_IMAGE_ENV, evaluator_build
from internal_api.schemas import Assignment, State
from server.challenges.evaluator_image import WORKERS_OWN
from server.challenges.quota import quota_use
from server.challenges.service import get_challenge
from server.kit.settings import Settings
from server.models import Cause, User, utcnow
from testkit.factories import make_challenge, make_user, queue_submission
from testkit.k8s_double import (
    CONTROLLERS,
    EVALUATOR_IMAGE,
    NAMESPACE,
    ApiServerDouble,
    running_apiserver,
)
from tests.deploy.test_operations import core_assignment
from tests.worker.test_k8s_worker import Run, attempt_end, k8s_worker, start, submission_of
from worker.kubernetes.manifest import build_job, job_name
from worker.kubernetes.spec import EvaluatorImageNotAllowed, job_spec
from worker.server_api import ServerAPI
from worker.settings import WorkerSettings

LAB = "127.0.0.1:5000/lab/evaluator-lab-tasks@sha256:" + "1a" * 32
OTHER = "127.0.0.1:5000/other/evaluator-tasks@sha256:" + "2b" * 32
TOKEN = "t" * 32


def settings_listing(*images: str) -> WorkerSettings:
    return WorkerSettings(
        worker_token=TOKEN,  # type: ignore[arg-type]
        executor="kubernetes",
        evaluator_image=EVALUATOR_IMAGE,
        evaluator_images=images,
    )


def handed(image: str | None) -> Assignment:
    return core_assignment().model_copy(update={"evaluator_image": image})


def evaluator_env(job: dict[str, object]) -> tuple[str, dict[str, str]]:
    (evaluator,) = job["spec"]["template"]["spec"]["containers"]  # type: ignore[index]
    return evaluator["image"], {e["name"]: e["value"] for e in evaluator["env"]}


@pytest.mark.parametrize(
    ("image", "runs_on"),
    [(LAB, LAB), (None, EVALUATOR_IMAGE), (EVALUATOR_IMAGE, EVALUATOR_IMAGE)],
    ids=["its-own-listed", "none-the-workers-own", "the-workers-own-by-name"],
)
def test_the_jobs_evaluator_runs_on_the_challenges_image_and_its_provenance_records_it(
    image: str | None, runs_on: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    job = build_job(job_spec(settings_listing(LAB), handed(image)))
    container_image, env = evaluator_env(job)
    assert container_image == runs_on
    # The evaluator records what the Job tells it in the result's provenance.
    monkeypatch.setenv(EVALUATOR_IMAGE_ENV, env[EVALUATOR_IMAGE_ENV])
    assert evaluator_build().image == runs_on


def test_an_image_the_workers_do_not_list_makes_no_job_and_says_what_to_configure() -> None:
    with pytest.raises(EvaluatorImageNotAllowed) as refused:
        job_spec(settings_listing(LAB), handed(OTHER))
    assert OTHER in str(refused.value)
    assert "add it to MANIEVAL_EVALUATOR_IMAGES" in str(refused.value)


def test_the_list_is_read_comma_or_space_separated_from_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MANIEVAL_WORKER_TOKEN", TOKEN)
    monkeypatch.setenv("MANIEVAL_EVALUATOR_IMAGE", EVALUATOR_IMAGE)
    monkeypatch.setenv("MANIEVAL_EVALUATOR_IMAGES", f" {LAB},\n  {OTHER} ")
    found = WorkerSettings()  # type: ignore[call-arg]
    assert found.evaluator_images == (LAB, OTHER)
    assert found.allowed_evaluator_images == {EVALUATOR_IMAGE, LAB, OTHER}


@pytest.mark.parametrize(
    "listed",
    ["127.0.0.1:5000/lab/evaluator-lab-tasks:0.1.0", "127.0.0.1:5000/lab/evaluator@sha256:1a"],
    ids=["tag", "short-digest"],
)
def test_a_listed_image_not_pinned_by_digest_stops_the_worker_at_start(
    listed: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MANIEVAL_WORKER_TOKEN", TOKEN)
    monkeypatch.setenv("MANIEVAL_EVALUATOR_IMAGES", f"{LAB} {listed}")
    with pytest.raises(ValidationError, match=f"MANIEVAL_EVALUATOR_IMAGES: {listed} is not pinned"):
        WorkerSettings()  # type: ignore[call-arg]


# Through the server's internal API and the API-server double --------------------------------


@pytest.fixture
def apiserver() -> Iterator[ApiServerDouble]:
    with running_apiserver(CONTROLLERS[-1]) as double:
        yield double


@pytest.fixture
def wsettings(settings: Settings, apiserver: ApiServerDouble) -> WorkerSettings:
    """Overrides the worker fixture: a Kubernetes worker that lists LAB."""
    return k8s_worker(settings, apiserver, evaluator_images=(LAB,))


def queued_on(sessions: sessionmaker[Session], image: str | None) -> int:
    with sessions() as db:
        challenge = make_challenge(db, evaluator_image=image or WORKERS_OWN)
        submission = queue_submission(db, make_user(db, "alice"), challenge)
        db.commit()
        return submission.id


@pytest.mark.long
@pytest.mark.parametrize(("image", "runs_on"), [(LAB, LAB), (None, EVALUATOR_IMAGE)])
def test_a_claimed_submissions_job_runs_on_its_challenges_image(
    committed_sessions: sessionmaker[Session],
    api: ServerAPI,
    wsettings: WorkerSettings,
    apiserver: ApiServerDouble,
    image: str | None,
    runs_on: str,
) -> None:
    sid = queued_on(committed_sessions, image)
    run = start(api, wsettings, committed_sessions, apiserver, sid)
    job = apiserver.jobs[(NAMESPACE, job_name(sid, 1))]
    assert evaluator_env(job)[0] == runs_on
    assert evaluator_env(job)[1][EVALUATOR_IMAGE_ENV] == runs_on
    apiserver.fail(NAMESPACE, job_name(sid, 1))
    run.wait()


@pytest.mark.long
def test_an_image_the_workers_do_not_list_ends_error_as_the_configurations_doing(
    committed_sessions: sessionmaker[Session],
    settings: Settings,
    api: ServerAPI,
    apiserver: ApiServerDouble,
) -> None:
    sid = queued_on(committed_sessions, OTHER)
    assert Run(api, k8s_worker(settings, apiserver), committed_sessions).wait() == State.ERROR
    assert apiserver.jobs == {}
    end = attempt_end(committed_sessions, sid)
    assert (end.to_state, end.cause) == (State.ERROR, Cause.CONFIGURATION)
    assert OTHER in end.reason
    assert "MANIEVAL_EVALUATOR_IMAGES" in end.reason
    submission = submission_of(committed_sessions, sid)
    assert (submission.state, submission.attempt) == (State.ERROR, 1)  # not queued again
    with committed_sessions() as db:
        user = db.get(User, submission.user_id)
        assert user is not None
        challenge = get_challenge(db, slug="server-tiny")
        use = quota_use(db, user=user, challenge=challenge, now=utcnow())
    assert use.per_day_used == 0  # not the participant's: no quota
