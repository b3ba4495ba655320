import numpy as np

from evaluator.conditions import ConditionRuntime
from evaluator.suite import ActionDelay, Condition, LowFreq, Nominal, ObsNoise


def runtime(params: object) -> ConditionRuntime:
    return ConditionRuntime(Condition(name="c", params=params))  # type: ignore[arg-type]


def obs(value: float) -> dict[str, object]:
    return {"pos": np.full(3, value, dtype=np.float32), "grasped": np.array(False)}


def test_nominal_passes_observations_through_unchanged():
    r = runtime(Nominal())
    first = obs(1.0)
    assert r.begin_episode(7, first) is first
    later = obs(2.0)
    assert r.observe(later) is later
    assert r.env_kwargs() == {}
    assert r.step_limit(100, 20) == 100


def test_obs_noise_perturbs_floats_only_and_repeats_for_the_same_seed():
    first, second = runtime(ObsNoise(sigma=0.1)), runtime(ObsNoise(sigma=0.1))
    a = first.begin_episode(7, obs(1.0))
    b = second.begin_episode(7, obs(1.0))
    np.testing.assert_array_equal(a["pos"], b["pos"])
    assert not np.array_equal(a["pos"], obs(1.0)["pos"])
    assert a["pos"].dtype == np.float32
    assert a["grasped"] is not None
    assert not a["grasped"]


def test_obs_noise_differs_between_seeds():
    r = runtime(ObsNoise(sigma=0.1))
    a = r.begin_episode(1, obs(1.0))["pos"]
    b = r.begin_episode(2, obs(1.0))["pos"]
    assert not np.array_equal(a, b)


def test_action_delay_shows_observations_k_steps_old():
    r = runtime(ActionDelay(steps=2))
    seen = [r.begin_episode(0, obs(0.0))["pos"][0]]
    seen += [r.observe(obs(float(t)))["pos"][0] for t in range(1, 6)]
    assert seen == [0.0, 0.0, 0.0, 1.0, 2.0, 3.0]


def test_action_delay_history_restarts_each_episode():
    r = runtime(ActionDelay(steps=1))
    r.begin_episode(0, obs(0.0))
    r.observe(obs(5.0))
    assert r.begin_episode(1, obs(9.0))["pos"][0] == 9.0


def test_low_freq_sets_the_control_rate_and_keeps_simulated_time():
    r = runtime(LowFreq(control_freq=5))
    assert r.env_kwargs() == {"sim_config": {"control_freq": 5}}
    assert r.step_limit(100, 20) == 25
    assert r.step_limit(50, 20) == 13
    assert r.step_limit(1, 20) == 1
