"""Trajectories on the server: stored through ``/internal/v1`` beside the videos, listed and
downloaded by whoever may see the submission in a public-seed phase, by organizers only in a
secret-seed one, and a clear 404 when none were recorded."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from internal_api.schemas import FinalReport
from server.kit.settings import Settings
from server.models import State
from server.submissions.reports import report_final, report_state
from server.submissions.video_store import HDF5_SIGNATURE
from server.submissions.videos import video_store
from testkit.factories import (
    RecordingQueue,
    make_challenge,
    make_user,
    queue_submission,
    result_doc,
    token_for,
)
from testkit.trajectories import episode_indices, write_part
from testkit.workers import server_api, server_app, worker_settings
from worker.server_api import ServerAPI

API = "/api/v1"
IMAGE = "127.0.0.1:5000/team/policy:v1"
STEM = "nominal--PickCube-v1"
H5 = HDF5_SIGNATURE + b"\x00" * 1000
JSON = json.dumps({"env_info": {"env_id": "PickCube-v1"}, "episodes": []}).encode()
UPLOAD = "/internal/v1/submissions/{sid}/attempts/1/trajectories/{name}"


@pytest.fixture
def setup(client: TestClient, db: Session) -> dict[str, dict[str, str]]:
    make_challenge(db, quota_per_day=10, quota_concurrent=10)
    for name in ("alice", "bob"):
        make_user(db, name)
    make_user(db, "judge", admin=True)
    return {name: token_for(client, name) for name in ("alice", "bob", "judge")}


def finished(
    client: TestClient,
    db: Session,
    settings: Settings,
    headers: dict[str, str],
    *,
    phase: str = "dev",
    public: bool = True,
    stored: bool = True,
) -> int:
    """A submission of alice's that succeeded, its nominal PickCube trajectories stored."""
    body = {"challenge": "server-tiny", "phase": phase, "image": IMAGE, "public": public}
    r = client.post(f"{API}/submissions", json=body, headers=headers)
    assert r.status_code == 202, r.text
    sid = int(r.json()["id"])
    assert report_state(db, sid, 1, State.LAUNCHING, "starting")
    assert report_state(db, sid, 1, State.RUNNING, "evaluating")
    result = result_doc([True, False], phase=phase)
    assert report_final(db, sid, 1, State.SUCCEEDED, "done", result=result)
    db.commit()
    if stored:
        store = video_store(settings)
        for name, data in ((f"{STEM}.h5", H5), (f"{STEM}.json", JSON)):
            store.store_trajectory(submission_id=sid, attempt=1, name=name, data=data)
    return sid


def test_a_public_seed_phases_trajectories_go_to_whoever_may_see_the_submission(
    client: TestClient, db: Session, settings: Settings, setup: dict[str, dict[str, str]]
) -> None:
    alice, bob, judge = setup["alice"], setup["bob"], setup["judge"]
    public = finished(client, db, settings, alice)
    private = finished(client, db, settings, alice, public=False)
    for sid, viewers, strangers in (
        (public, (alice, bob, judge, {}), ()),
        (private, (alice, judge), (bob, {})),
    ):
        for headers in viewers:
            r = client.get(f"{API}/submissions/{sid}/trajectories", headers=headers)
            assert r.status_code == 200, r.text
            (listed,) = r.json()["trajectories"]
            assert (listed["condition"], listed["env_id"], listed["episodes"]) == (
                "nominal",
                "PickCube-v1",
                2,
            )
            assert listed["bytes"] == len(H5) + len(JSON)
            h5 = client.get(listed["h5_url"], headers=headers)
            assert h5.status_code == 200
            assert h5.content == H5
            assert h5.headers["content-type"] == "application/x-hdf5"
            assert f'filename="{STEM}.h5"' in h5.headers["content-disposition"]
            assert client.get(listed["json_url"], headers=headers).json() == json.loads(JSON)
        for headers in strangers:
            assert (
                client.get(f"{API}/submissions/{sid}/trajectories", headers=headers).status_code
                == 404
            )
            r = client.get(f"{API}/submissions/{sid}/trajectories/{STEM}.h5", headers=headers)
            assert r.status_code == 404


def test_a_secret_seed_phases_trajectories_go_to_organizers_only(
    client: TestClient, db: Session, settings: Settings, setup: dict[str, dict[str, str]]
) -> None:
    alice, bob, judge = setup["alice"], setup["bob"], setup["judge"]
    public = finished(client, db, settings, alice, phase="test")
    private = finished(client, db, settings, alice, phase="test", public=False)
    for sid in (public, private):
        r = client.get(f"{API}/submissions/{sid}/trajectories", headers=judge)
        assert r.status_code == 200, r.text
        assert (
            client.get(f"{API}/submissions/{sid}/trajectories/{STEM}.h5", headers=judge).content
            == H5
        )
    # Its owner, and anyone who may see the public one: it exists, its trajectories are refused.
    for sid, headers in ((public, alice), (public, bob), (public, {}), (private, alice)):
        for path in ("trajectories", f"trajectories/{STEM}.h5", f"trajectories/{STEM}.json"):
            r = client.get(f"{API}/submissions/{sid}/{path}", headers=headers)
            assert r.status_code == 403, r.text
            assert "visible to organizers only" in r.json()["error"]["message"]
    for headers in (bob, {}):
        assert (
            client.get(f"{API}/submissions/{private}/trajectories", headers=headers).status_code
            == 404
        )


def test_a_submission_without_trajectories_says_so_and_unlisted_names_are_404(
    client: TestClient, db: Session, settings: Settings, setup: dict[str, dict[str, str]]
) -> None:
    alice = setup["alice"]
    bare = finished(client, db, settings, alice, stored=False)
    r = client.get(f"{API}/submissions/{bare}/trajectories", headers=alice)
    assert r.status_code == 404
    assert r.json()["error"]["message"].startswith(
        f"submission {bare} has no recorded trajectories"
    )
    assert (
        client.get(f"{API}/submissions/{bare}/trajectories/{STEM}.h5", headers=alice).status_code
        == 404
    )
    sid = finished(client, db, settings, alice)
    for name in ("obs_noise--PickCube-v1.h5", "nominal--PushCube-v1.json", "..%2Fx.h5", "x.txt"):
        r = client.get(f"{API}/submissions/{sid}/trajectories/{name}", headers=alice)
        assert r.status_code == 404, name


def test_the_submission_page_links_the_trajectories_for_those_who_may_download_them(
    client: TestClient, db: Session, settings: Settings, setup: dict[str, dict[str, str]]
) -> None:
    alice = setup["alice"]
    dev = finished(client, db, settings, alice)
    secret = finished(client, db, settings, alice, phase="test")
    page = client.get(f"/submissions/{dev}").text
    assert f'href="/api/v1/submissions/{dev}/trajectories/{STEM}.h5"' in page
    assert f"manieval trajectories {dev}" in page
    assert "/trajectories/" not in client.get(f"/submissions/{secret}").text


# Uploads from the worker ----------------------------------------------------------------------


@pytest.fixture
def app(
    settings: Settings, committed_sessions: sessionmaker[Session], work: RecordingQueue
) -> FastAPI:
    small = settings.model_copy(update={"max_trajectory_bytes": 64 * 1024})
    return server_app(small, committed_sessions, work)


@pytest.fixture
def api(app: FastAPI, settings: Settings) -> Iterator[ServerAPI]:
    client = server_api(app, worker_settings(settings))
    yield client
    client.close()


@pytest.fixture
def running(committed_sessions: sessionmaker[Session], api: ServerAPI) -> int:
    with committed_sessions() as session:
        challenge = make_challenge(session, quota_concurrent=10, quota_per_day=10)
        sid = queue_submission(session, make_user(session, "carol"), challenge).id
        session.commit()
    assert api.claim("w1") is not None
    assert api.running(sid, 1, reason="evaluating", deadline_s=600) is not None
    return sid


def test_a_running_attempts_trajectory_files_are_kept_beside_its_videos(
    api: ServerAPI, running: int, settings: Settings, tmp_path: Path
) -> None:
    for name, data in ((f"{STEM}.h5", H5), (f"{STEM}.json", JSON)):
        (tmp_path / name).write_bytes(data)
        assert api.upload_trajectory(running, 1, tmp_path / name) is True
    directory = settings.data_dir / "videos" / str(running) / "1" / "trajectories"
    assert sorted(p.name for p in directory.iterdir()) == [f"{STEM}.h5", f"{STEM}.json"]
    assert (directory / f"{STEM}.h5").read_bytes() == H5


@pytest.mark.parametrize(
    ("name", "media", "body", "status"),
    [
        ("evil.sh", "application/x-hdf5", H5, 415),
        ("nominal--PickCube-v1.h5.part", "application/x-hdf5", H5, 415),
        ("nominal--PickCube.h5", "application/x-hdf5", H5, 422),
        (f"{STEM}.h5", "application/json", H5, 415),
        (f"{STEM}.h5", "application/x-hdf5", b"not hdf5" * 10, 415),
        (f"{STEM}.json", "application/json", b'{"episodes": []}', 415),
        (f"{STEM}.h5", "application/x-hdf5", H5 + b"\x00" * 64 * 1024, 413),
    ],
)
def test_uploads_that_are_not_a_bounded_trajectory_file_of_an_expected_name_are_refused(
    app: FastAPI, settings: Settings, running: int, name: str, media: str, body: bytes, status: int
) -> None:
    headers = {"Authorization": f"Bearer {settings.secret('worker_token')}", "Content-Type": media}
    with TestClient(app, base_url="http://testserver", headers=headers) as http:
        r = http.put(UPLOAD.format(sid=running, name=name), content=body)
    assert r.status_code == status, r.text
    assert not (settings.data_dir / "videos" / str(running) / "1" / "trajectories").exists()


def test_trajectories_are_refused_for_attempts_that_do_not_run(
    api: ServerAPI, running: int, tmp_path: Path
) -> None:
    path = tmp_path / f"{STEM}.h5"
    path.write_bytes(H5)
    assert api.upload_trajectory(running, 2, path) is False


def test_parts_a_kubernetes_job_wrote_are_merged_when_the_final_report_comes(
    api: ServerAPI, running: int, settings: Settings
) -> None:
    """Each pod of a sharded Job writes its part into the attempt's directory on the video
    volume (`evaluator.job`); the final report merges them, and a resent report changes nothing."""
    directory = settings.data_dir / "videos" / str(running) / "1" / "trajectories"
    write_part(directory, STEM, first=0, episodes=1)
    write_part(directory, STEM, first=1, episodes=1)
    report = FinalReport(state=State.SUCCEEDED, reason="done", result=result_doc([True, False]))
    assert api.final(running, 1, report) is State.SUCCEEDED
    assert sorted(p.name for p in directory.iterdir()) == [f"{STEM}.h5", f"{STEM}.json"]
    assert episode_indices(directory / f"{STEM}.h5") == [0, 1]
    merged = (directory / f"{STEM}.json").read_bytes()
    assert api.final(running, 1, report) is State.SUCCEEDED
    assert (directory / f"{STEM}.json").read_bytes() == merged
