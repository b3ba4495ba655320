"""A challenge loaded as a try-out: fewer tasks, conditions or episodes, and the stored suite
says so (what `manieval demo` does with the visual track)."""

from __future__ import annotations

import pytest
import yaml

from evaluator.suite import SuiteError, load_suite
from server.challenges.service import ChallengeOptions, try_out


def test_a_try_out_keeps_only_the_named_tasks_and_conditions_with_their_videos():
    suite = load_suite("maniskill-visual")
    options = ChallengeOptions(
        tasks=("PushCube-v1",), conditions=("nominal", "low_freq"), episodes=1
    )
    narrowed, said = try_out(suite, options)
    assert [(t.env_id, t.episodes, t.obs_mode) for t in narrowed.tasks] == [
        ("PushCube-v1", 1, "rgbd")
    ]
    assert narrowed.tasks[0].instruction == suite.task("PushCube-v1").instruction
    assert [c.name for c in narrowed.conditions] == ["nominal", "low_freq"]
    assert narrowed.video_conditions == ("nominal",)
    assert narrowed.observation_keys == suite.observation_keys
    assert said == [
        "only the task PushCube-v1",
        "1 episodes per task",
        "only the conditions nominal, low_freq",
    ]
    stored = yaml.safe_dump(narrowed.model_dump(mode="json"))
    assert narrowed.sha256() != suite.sha256()
    assert yaml.safe_load(stored)["tasks"][0]["env_id"] == "PushCube-v1"


def test_a_suite_left_whole_is_not_a_try_out():
    suite = load_suite("maniskill-core")
    narrowed, said = try_out(suite, ChallengeOptions())
    assert narrowed is suite
    assert said == []


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (ChallengeOptions(tasks=("NoSuchTask-v1",)), "no task 'NoSuchTask-v1'"),
        (ChallengeOptions(conditions=("storm",)), "no condition 'storm'"),
    ],
)
def test_a_try_out_refuses_names_the_suite_lacks(options: ChallengeOptions, message: str):
    with pytest.raises(SuiteError, match=message):
        try_out(load_suite("maniskill-visual"), options)
