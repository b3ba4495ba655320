from pathlib import Path

import pytest

from evaluator.job import evaluation_job
from evaluator.plan import build_plan
from evaluator.suite import (
    PolicyResources,
    SuiteError,
    load_suite,
    phase_seeds,
    seed_commitment,
)

CORE_TASKS = {
    "PickCube-v1",
    "PushCube-v1",
    "PullCube-v1",
    "StackCube-v1",
    "PegInsertionSide-v1",
    "LiftPegUpright-v1",
}


def write_suite(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "suite.yaml"
    path.write_text(body)
    return path


def test_bundled_core_suite_loads_by_name_with_its_tasks_and_conditions():
    suite = load_suite("maniskill-core")
    assert {t.env_id for t in suite.tasks} == CORE_TASKS
    assert [c.name for c in suite.conditions] == [
        "nominal",
        "obs_noise",
        "action_delay",
        "low_freq",
    ]
    assert set(suite.phases) == {"dev", "test"}


def test_dev_seeds_are_public_and_consecutive():
    suite = load_suite("maniskill-core")
    assert phase_seeds(suite, "dev", "PickCube-v1", 4) == [0, 1, 2, 3]


def test_test_seeds_need_the_secret():
    suite = load_suite("maniskill-core")
    with pytest.raises(SuiteError, match="secret"):
        phase_seeds(suite, "test", "PickCube-v1", 3)


def test_test_seeds_are_stable_per_secret_and_differ_between_secrets_and_tasks():
    suite = load_suite("maniskill-core")
    a = phase_seeds(suite, "test", "PickCube-v1", 5, secret=b"s1")
    assert a == phase_seeds(suite, "test", "PickCube-v1", 5, secret=b"s1")
    assert a != phase_seeds(suite, "test", "PickCube-v1", 5, secret=b"s2")
    assert a != phase_seeds(suite, "test", "PushCube-v1", 5, secret=b"s1")
    assert all(0 <= s < 2**31 for s in a)


def test_seed_commitment_changes_with_any_seed():
    base = seed_commitment({"PickCube-v1": [1, 2]}, salt="x")
    assert len(base) == 64
    assert base == seed_commitment({"PickCube-v1": [1, 2]}, salt="x")
    assert base != seed_commitment({"PickCube-v1": [1, 3]}, salt="x")


def test_suite_hash_is_stable_and_changes_with_content(tmp_path: Path):
    suite = load_suite("maniskill-core")
    assert suite.sha256() == load_suite("maniskill-core").sha256()
    text = (Path(__file__).parents[2] / "suites" / "maniskill-core.yaml").read_text()
    changed = load_suite(write_suite(tmp_path, text.replace("sigma: 0.005", "sigma: 0.01")))
    assert changed.sha256() != suite.sha256()
    assert suite.model_copy(update={"shards": 8}).sha256() == suite.sha256()  # where, not what
    assert suite.model_copy(update={"title": "Another Name"}).sha256() == suite.sha256()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("name: x\nversion: 1\ntasks: []\nphases: {dev: {seeds: {kind: public}}}", "tasks"),
        ("name: x\nversion: 1\ntasks: [{env_id: PickCube-v1}]\nphases: {}", "max_episode_steps"),
        (
            "name: x\nversion: 1\nbogus: 1\ntasks: [{env_id: A-v1, max_episode_steps: 5}]\n"
            "phases: {dev: {seeds: {kind: public}}}",
            "bogus",
        ),
        (
            "name: x\nversion: 1\ntasks: [{env_id: A-v1, max_episode_steps: 5}, "
            "{env_id: A-v1, max_episode_steps: 5}]\nphases: {dev: {seeds: {kind: public}}}",
            "duplicate task",
        ),
        ("name: x\nversion: [", "not valid YAML"),
    ],
)
def test_invalid_suites_are_refused_with_a_reason(tmp_path: Path, body: str, message: str):
    with pytest.raises(SuiteError, match=message):
        load_suite(write_suite(tmp_path, body))


def test_unknown_suite_name_lists_the_bundled_ones():
    with pytest.raises(SuiteError, match="maniskill-core"):
        load_suite("no-such-suite")


def test_plan_narrows_tasks_conditions_and_episodes():
    plan = build_plan(
        load_suite("maniskill-core"),
        "dev",
        tasks=["PushCube-v1"],
        conditions=["nominal", "low_freq"],
        episodes=3,
    )
    assert [(r.condition.name, r.env_id, r.seeds) for r in plan.runs] == [
        ("nominal", "PushCube-v1", (0, 1, 2)),
        ("low_freq", "PushCube-v1", (0, 1, 2)),
    ]
    assert plan.episode_count() == 6


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"tasks": ["NoSuchTask-v1"]}, "no task 'NoSuchTask-v1'"),
        ({"conditions": ["storm"]}, "no condition 'storm'"),
        ({"episodes": 0}, "at least 1"),
    ],
)
def test_plan_refuses_unknown_names(kwargs: dict[str, object], message: str):
    with pytest.raises(SuiteError, match=message):
        build_plan(load_suite("maniskill-core"), "dev", **kwargs)  # type: ignore[arg-type]


def test_plan_refuses_unknown_phase():
    with pytest.raises(SuiteError, match="no phase 'final'"):
        build_plan(load_suite("maniskill-core"), "final")


# The core suite's hash before `ignore_terminations` existed: challenges store it.
CORE_SUITE_SHA256 = "cdef3d03c550f38c49ad1f0bf92bcce0ccdb67c81feb01fa31027f35b21ebf13"


def test_a_suite_that_leaves_a_newer_setting_at_its_default_keeps_its_hash():
    suite = load_suite("maniskill-core")
    assert suite.ignore_terminations is False
    assert suite.sha256() == CORE_SUITE_SHA256
    assert suite.model_copy(update={"ignore_terminations": True}).sha256() != CORE_SUITE_SHA256


def test_ignore_terminations_travels_from_the_suite_into_the_plan(tmp_path: Path):
    text = (Path(__file__).parents[2] / "suites" / "maniskill-core.yaml").read_text()
    suite = load_suite(write_suite(tmp_path, text + "ignore_terminations: true\n"))
    assert build_plan(suite, "dev").ignore_terminations is True
    assert build_plan(load_suite("maniskill-core"), "dev").ignore_terminations is False


def test_a_gpu_request_for_the_policy_reaches_the_plan_and_the_job_but_not_the_hash(
    tmp_path: Path,
):
    text = (Path(__file__).parents[2] / "suites" / "maniskill-core.yaml").read_text()
    suite = load_suite(write_suite(tmp_path, text + "policy: {gpus: 2}\n"))
    assert suite.policy.gpus == 2
    assert load_suite("maniskill-core").policy.gpus == 0  # the default: none
    # Hardware makes a policy faster, not its scores other: the same suite, the same hash.
    assert suite.sha256() == CORE_SUITE_SHA256
    plan = build_plan(suite, "dev", episodes=1)
    assert plan.policy.gpus == 2
    assert evaluation_job(plan, suite_yaml=text + "policy: {gpus: 2}\n").plan() == plan


@pytest.mark.parametrize(
    ("policy", "message"),
    [
        ("{gpus: -1}", "greater than or equal to 0"),
        ("{gpus: 9}", "less than or equal to 8"),
        ("{cpus: 4}", "cpus"),
    ],
)
def test_an_invalid_policy_section_is_refused(tmp_path: Path, policy: str, message: str):
    text = (Path(__file__).parents[2] / "suites" / "maniskill-core.yaml").read_text()
    with pytest.raises(SuiteError, match=message):
        load_suite(write_suite(tmp_path, text + f"policy: {policy}\n"))


def test_a_service_without_enough_gpus_says_why_it_cannot_run_the_policy():
    assert PolicyResources().refusal(available=0) is None
    assert PolicyResources(gpus=1).refusal(available=1) is None
    assert PolicyResources(gpus=1).refusal(available=0) == (
        "this challenge asks for 1 GPU per policy, and this service has none for policies "
        "(its operator sets MANIEVAL_POLICY_GPUS)"
    )
    assert "2 GPUs per policy, and this service has at most 1" in str(
        PolicyResources(gpus=2).refusal(available=1)
    )


VISUAL_KEYS = (
    "agent/qpos",
    "agent/qvel",
    "extra/tcp_pose",
    "extra/goal_pos",
    "sensor_param",
    "sensor_data/*/rgb",
    "sensor_data/*/depth",
    "pointcloud/xyzw",
    "pointcloud/rgb",
)


def test_the_visual_suite_runs_the_core_tasks_on_cameras_with_an_instruction_each():
    suite = load_suite("maniskill-visual")
    assert {t.env_id for t in suite.tasks} == CORE_TASKS
    assert {t.obs_mode for t in suite.tasks} == {"rgbd"}
    assert all(t.instruction for t in suite.tasks)
    assert suite.observation_keys == VISUAL_KEYS
    assert [c.name for c in suite.conditions] == [
        "nominal",
        "pointcloud",
        "action_delay",
        "low_freq",
    ]
    assert set(suite.phases) == {"dev", "test"}


def test_an_obs_mode_condition_shows_the_tasks_through_another_observation_mode():
    plan = build_plan(load_suite("maniskill-visual"), "dev", tasks=["PickCube-v1"], episodes=1)
    assert {r.condition.name: r.obs_mode for r in plan.runs} == {
        "nominal": "rgbd",
        "pointcloud": "pointcloud",
        "action_delay": "rgbd",
        "low_freq": "rgbd",
    }
    assert {r.instruction for r in plan.runs} == {
        load_suite("maniskill-visual").tasks[0].instruction
    }
    assert {r.observation_keys for r in plan.runs} == {VISUAL_KEYS}


def test_the_job_a_pod_runs_keeps_the_instruction_keys_and_obs_mode(tmp_path: Path):
    from evaluator.job import evaluation_job

    path = Path(__file__).parents[2] / "suites" / "maniskill-visual.yaml"
    plan = build_plan(load_suite(path), "dev", tasks=["PushCube-v1"], episodes=2)
    assert evaluation_job(plan, suite_yaml=path.read_text()).plan().runs == plan.runs


def test_an_instruction_and_observation_keys_enter_the_hash_only_when_set():
    suite = load_suite("maniskill-core")
    tasks = suite.tasks
    worded = (tasks[0].model_copy(update={"instruction": "Pick it up."}), *tasks[1:])
    assert suite.model_copy(update={"tasks": worded}).sha256() != CORE_SUITE_SHA256
    assert suite.model_copy(update={"observation_keys": ("agent",)}).sha256() != CORE_SUITE_SHA256
    unworded = (tasks[0].model_copy(update={"instruction": ""}), *tasks[1:])
    assert suite.model_copy(update={"tasks": unworded}).sha256() == CORE_SUITE_SHA256


@pytest.mark.parametrize(
    ("obs_mode", "extra", "message"),
    [
        ("state", "observation_keys: [agent/qpos]", "obs_mode state gives one flat array"),
        (
            "rgbd",
            "conditions: [{name: s, params: {kind: obs_mode, obs_mode: state}}]\n"
            "observation_keys: [agent/qpos]",
            "obs_mode state gives one flat array",
        ),
        ("rgbd", "observation_keys: ['agent//qpos']", "observation_keys.0\n.*pattern"),
        (
            "rgbd",
            "conditions: [{name: n, params: {kind: obs_mode, obs_mode: 'point cloud'}}]",
            "obs_mode\n.*pattern",
        ),
    ],
)
def test_observation_settings_that_cannot_work_are_refused(
    tmp_path: Path, obs_mode: str, extra: str, message: str
):
    body = (
        "name: x\nversion: 1\n"
        f"tasks: [{{env_id: A-v1, max_episode_steps: 5, obs_mode: {obs_mode}}}]\n"
        f"phases: {{dev: {{seeds: {{kind: public}}}}}}\n{extra}\n"
    )
    with pytest.raises(SuiteError, match=message):
        load_suite(write_suite(tmp_path, body))


def test_a_phases_significance_level_is_checked_and_stays_out_of_the_hash(tmp_path: Path):
    core = load_suite("maniskill-core")
    assert {p.significance_level for p in core.phases.values()} == {0.05}
    text = (Path(__file__).parents[2] / "suites" / "maniskill-core.yaml").read_text()
    stricter = text.replace(
        "seeds: {kind: secret}", "seeds: {kind: secret}\n    significance_level: 0.01"
    )
    suite = load_suite(write_suite(tmp_path, stricter))
    assert suite.phase("test").significance_level == 0.01
    assert suite.sha256() == CORE_SUITE_SHA256  # how results are read, not what ran
    for bad in ("0", "0.6", "-0.1"):
        wrong = text.replace(
            "seeds: {kind: secret}", f"seeds: {{kind: secret}}\n    significance_level: {bad}"
        )
        with pytest.raises(SuiteError, match="significance_level"):
            load_suite(write_suite(tmp_path, wrong))
