"""Episode videos and trajectories on Kubernetes: the evaluator, never the policy, mounts the
attempt's directory of the video volume when a claim is set; it writes videos there when the
suite records them, and every episode's trajectory, which the server merges at the final
report."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest

from evaluator.job import (
    TRAJECTORY_DIR_ENV,
    VIDEO_DIR_ENV,
    EvaluationJob,
    ExternalPolicy,
    result_from_logs,
    run_job,
)
from evaluator.trajectory import PARTS, trajectory_stem
from internal_api.schemas import Assignment
from server.kit.settings import Settings
from server.submissions.trajectories import merge_written
from server.submissions.video_store import VideoStore
from testkit.k8s_double import (
    POLICY_IMAGE,
)
from testkit.trajectories import episode_indices
from testkit.workers import worker_settings
from tests.worker.k8s_specs import (
    make_spec,
    tiny_evaluation,
)
from tests.worker.test_evaluate_job import printed, start_policy
from worker.kubernetes.manifest import TRAJECTORY_MOUNT_DIR, VIDEO_MOUNT, build_job
from worker.kubernetes.spec import job_spec

Json = dict[str, Any]


def pod_of(manifest: Json) -> Json:
    pod: Json = manifest["spec"]["template"]["spec"]
    return pod


def recording_evaluation() -> EvaluationJob:
    job = tiny_evaluation()
    return job.model_copy(update={"suite_yaml": job.suite_yaml + "videos: 1\n"})


def test_the_evaluator_alone_mounts_the_attempts_video_directory():
    spec = make_spec(submission_id=42, attempt=3, video_claim="videos-rwx", videos=True)
    pod = pod_of(build_job(spec))
    assert {"name": "videos", "persistentVolumeClaim": {"claimName": "videos-rwx"}} in pod[
        "volumes"
    ]
    [evaluator] = pod["containers"]
    assert {"name": "videos", "mountPath": VIDEO_MOUNT, "subPath": "42/3"} in evaluator[
        "volumeMounts"
    ]
    assert {"name": VIDEO_DIR_ENV, "value": VIDEO_MOUNT} in evaluator["env"]
    assert {"name": TRAJECTORY_DIR_ENV, "value": TRAJECTORY_MOUNT_DIR} in evaluator["env"]
    [policy] = pod["initContainers"]
    assert all(m["name"] != "videos" for m in policy["volumeMounts"])
    names = {e["name"] for e in policy.get("env", [])}
    assert not names & {VIDEO_DIR_ENV, TRAJECTORY_DIR_ENV}


@pytest.mark.parametrize("version", ["1.30"])
def test_a_job_with_a_video_volume_validates_strictly(version: str):
    manifest = build_job(make_spec(video_claim="manieval-videos"))
    assert kubernetes_validate.validate(manifest, version, strict=True)


def test_without_a_claim_there_is_no_video_volume():
    pod = pod_of(build_job(make_spec()))
    assert all(v["name"] != "videos" for v in pod["volumes"])
    names = {e["name"] for e in pod["containers"][0]["env"]}
    assert not names & {VIDEO_DIR_ENV, TRAJECTORY_DIR_ENV}


def test_a_claim_that_is_not_a_name_is_refused():
    with pytest.raises(ValueError, match="video claim"):
        make_spec(video_claim="../etc")


@pytest.mark.parametrize("suite_videos", [True, False])
def test_the_worker_mounts_the_claim_for_trajectories_and_asks_for_videos_where_recorded(
    settings: Settings, suite_videos: bool
):
    wsettings = worker_settings(settings, k8s_video_claim="manieval-videos")
    evaluation = recording_evaluation() if suite_videos else tiny_evaluation()
    spec = make_spec(evaluation=evaluation)
    handed = Assignment(
        submission_id=7,
        attempt=1,
        plan=evaluation.plan(),
        suite_yaml=evaluation.suite_yaml,
        image=spec.policy_image,
        shards=1,
    )
    pod = pod_of(
        build_job(job_spec(wsettings.model_copy(update={"evaluator_image": "e:1"}), handed))
    )
    assert any(v["name"] == "videos" for v in pod["volumes"])
    names = {e["name"] for e in pod["containers"][0]["env"]}
    assert TRAJECTORY_DIR_ENV in names
    assert (VIDEO_DIR_ENV in names) is suite_videos


@pytest.mark.sim
def test_pods_write_their_shards_recordings_to_the_volume_and_the_server_merges_trajectories(
    tmp_path: Path,
):
    evaluation = recording_evaluation().model_copy(
        update={"seeds": {"PickCube-v1": (100, 101, 102)}}
    )
    plan = evaluation.plan()
    assert plan.videos == 1
    store = VideoStore(tmp_path / "store", max_bytes=10**8, max_per_attempt=10)
    videos = store.attempt_dir(submission_id=42, attempt=3)  # the pods' subPath of the volume
    logs = []
    for index in range(2):
        endpoint = Path(tempfile.mkdtemp(prefix="mev-"))  # sockets want a short path
        policy = start_policy(endpoint)
        try:
            report = run_job(
                plan,
                ExternalPolicy(POLICY_IMAGE),
                index=index,
                shards=2,
                socket_dir=endpoint,
                video_dir=videos,
                trajectory_dir=videos / "trajectories",
            )
        finally:
            policy.kill()
            shutil.rmtree(endpoint, ignore_errors=True)
        logs.append(printed(report))
    merged = result_from_logs(plan, logs)
    assert [(v.condition, v.env_id, v.episode) for v in merged.videos] == [
        ("nominal", "PickCube-v1", 0)
    ]
    assert sorted(p.name for p in videos.iterdir()) == [  # the server serves the poster as is
        "nominal--PickCube-v1--ep0.mp4",
        "nominal--PickCube-v1--ep0.poster.jpg",
        "trajectories",
    ]
    stem = trajectory_stem(condition="nominal", env_id="PickCube-v1")
    assert len(list((videos / "trajectories" / PARTS).glob(f"{stem}--from*.h5"))) == 2
    merge_written(store, submission_id=42, attempt=3, result=merged)
    h5 = store.trajectory_path(submission_id=42, attempt=3, name=f"{stem}.h5")
    assert h5 is not None
    assert episode_indices(h5) == [0, 1, 2]
