"""McNemar's exact test against scipy, paired tables, and tie groups with Holm's correction."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import binomtest

from evaluator.paired import (
    Outcome,
    PackedOutcomes,
    PairedTable,
    compare,
    compare_packed,
    holm_rejections,
    tie_groups,
)
from evaluator.stats import mcnemar_exact_p, wilson_interval

# Below about 1e-300 scipy's own float arithmetic underflows before ours does (ours is exact,
# then rounded once): there the values are compared absolutely.
TINY = 1e-300


def scipy_p(b: int, c: int) -> float:
    return 1.0 if b + c == 0 else float(binomtest(min(b, c), b + c, 0.5).pvalue)


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        st.tuples(st.integers(0, 40), st.integers(0, 40)),
        st.tuples(st.integers(0, 3000), st.integers(0, 3000)),
        st.integers(0, 3000).map(lambda n: (n, max(0, n - 60))),  # near-balanced, large
    )
)
def test_mcnemar_exact_p_equals_scipys_binomial_test(table: tuple[int, int]) -> None:
    b, c = table
    assert mcnemar_exact_p(b, c) == pytest.approx(scipy_p(b, c), rel=1e-12, abs=TINY)
    assert mcnemar_exact_p(b, c) == mcnemar_exact_p(c, b)


@pytest.mark.parametrize(
    ("b", "c", "p"),
    [(0, 0, 1.0), (1, 0, 1.0), (3, 3, 1.0), (5, 4, 1.0), (5, 0, 0.0625), (15, 0, 2**-14)],
)
def test_mcnemar_exact_p_known_values(b: int, c: int, p: float) -> None:
    assert mcnemar_exact_p(b, c) == p


def test_mcnemar_exact_p_refuses_negative_counts() -> None:
    with pytest.raises(ValueError, match="non-negative"):
        mcnemar_exact_p(-1, 2)


# Paired tables ---------------------------------------------------------------------------------


def outcomes(successes: list[bool], *, env_id: str = "PickCube-v1", condition: str = "nominal"):
    return [
        Outcome(condition=condition, env_id=env_id, index=i, seed=1000 + i, success=ok)
        for i, ok in enumerate(successes)
    ]


def pair_of(both: int, only_a: int, only_b: int, neither: int) -> tuple[list[bool], list[bool]]:
    """Two runs over the same episodes with this 2x2 table."""
    a = [True] * both + [True] * only_a + [False] * only_b + [False] * neither
    b = [True] * both + [False] * only_a + [True] * only_b + [False] * neither
    return a, b


def test_compare_counts_a_table_per_task_and_pools_them() -> None:
    a = outcomes([True, True, False, False]) + outcomes([True, False], env_id="StackCube-v1")
    b = outcomes([True, False, True, False]) + outcomes([False, False], env_id="StackCube-v1")
    found = compare(a, b, condition="nominal")
    assert found.tasks == {
        "PickCube-v1": PairedTable(both=1, only_a=1, only_b=1, neither=1),
        "StackCube-v1": PairedTable(both=0, only_a=1, only_b=0, neither=1),
    }
    assert found.pooled == PairedTable(both=1, only_a=2, only_b=1, neither=2)
    assert found.p_value == mcnemar_exact_p(2, 1)
    assert (found.unpaired_a, found.unpaired_b) == (0, 0)


def test_compare_pairs_only_the_named_condition_and_the_same_seeds() -> None:
    a = outcomes([True, True, True]) + outcomes([True], condition="obs_noise")
    b = outcomes([False, False]) + outcomes([False], condition="obs_noise")
    b.append(Outcome(condition="nominal", env_id="PickCube-v1", index=2, seed=99, success=True))
    found = compare(a, b, condition="nominal")
    assert found.pooled == PairedTable(only_a=2)
    assert (found.unpaired_a, found.unpaired_b) == (1, 1)  # index 2 ran different seeds


def test_compare_pairs_secret_seed_episodes_by_index() -> None:
    a = [Outcome("nominal", "PickCube-v1", i, None, True) for i in range(3)]
    b = [Outcome("nominal", "PickCube-v1", i, None, i == 0) for i in range(3)]
    assert compare(a, b, condition="nominal").pooled == PairedTable(both=1, only_a=2)


def test_compare_refuses_an_episode_listed_twice() -> None:
    with pytest.raises(ValueError, match="twice"):
        compare(outcomes([True]) * 2, outcomes([True]), condition="nominal")


# Packed outcomes: what a board compares ------------------------------------------------------

TASK_NAMES = ("PickCube-v1", "StackCube-v1", "PushCube-v1")


@st.composite
def runs(draw: st.DrawFn, *, seeds: dict[str, list[int]]) -> list[Outcome]:
    """A run of some of the tasks, over these seeds, under two conditions, in any order."""
    found = [
        Outcome(condition, env_id, i, seed, draw(st.booleans()))
        for env_id in draw(st.lists(st.sampled_from(TASK_NAMES), unique=True))
        for condition in ("nominal", "obs_noise")
        for i, seed in enumerate(seeds[env_id])
    ]
    return draw(st.permutations(found))


SEEDS = {name: [7 * n + i for i in range(70)] for n, name in enumerate(TASK_NAMES)}


@settings(max_examples=200, deadline=None)
@given(runs(seeds=SEEDS), runs(seeds=SEEDS))
def test_packed_outcomes_compare_as_the_outcomes_do(a: list[Outcome], b: list[Outcome]) -> None:
    packed = [PackedOutcomes.of(run, condition="nominal") for run in (a, b)]
    found = compare_packed(*packed)
    assert found == compare(a, b, condition="nominal")
    again = [PackedOutcomes.from_json(json.loads(json.dumps(p.as_json()))) for p in packed]
    assert again == packed


def test_packed_outcomes_with_other_seeds_are_compared_as_outcomes() -> None:
    a = PackedOutcomes.of(outcomes([True, False]), condition="nominal")
    moved = [Outcome("nominal", "PickCube-v1", i, 2000 + i, True) for i in range(2)]
    assert compare_packed(a, PackedOutcomes.of(moved, condition="nominal")) is None
    fewer = PackedOutcomes.of(outcomes([True]), condition="nominal")
    assert compare_packed(a, fewer) is None  # compare pairs the first one: so must the board


def test_packing_refuses_an_index_run_with_two_seeds() -> None:
    twice = [*outcomes([True]), Outcome("nominal", "PickCube-v1", 0, 5, False)]
    with pytest.raises(ValueError, match="twice"):
        PackedOutcomes.of(twice, condition="nominal")


def overlap(a: list[bool], b: list[bool]) -> bool:
    """The board's current rule: the two pooled Wilson intervals overlap (tied)."""
    low_a, high_a = wilson_interval(sum(a), len(a))
    low_b, high_b = wilson_interval(sum(b), len(b))
    return low_a <= high_b and low_b <= high_a


def test_overlapping_intervals_yet_the_paired_test_separates() -> None:
    # A solves every episode B solves, and 15 more of the 100: 65 against 50.
    a, b = pair_of(both=50, only_a=15, only_b=0, neither=35)
    assert overlap(a, b)
    found = compare(outcomes(a), outcomes(b), condition="nominal")
    assert found.p_value == pytest.approx(2**-14)
    assert found.significant()


def test_separate_intervals_yet_the_paired_test_does_not_separate() -> None:
    # 58 against 38 of 100, but on 96 discordant episodes: B wins 38 of them.
    a, b = pair_of(both=0, only_a=58, only_b=38, neither=4)
    assert not overlap(a, b)
    found = compare(outcomes(a), outcomes(b), condition="nominal")
    assert found.p_value == pytest.approx(scipy_p(58, 38), rel=1e-12)
    assert 0.05 < found.p_value < 0.06
    assert not found.significant()


def test_few_episodes_separate_intervals_yet_no_exact_test_can_separate() -> None:
    # 5 of 5 against 0 of 5: the intervals are apart, but 5 discordant pairs cannot reach 0.05.
    a, b = pair_of(both=0, only_a=5, only_b=0, neither=0)
    assert not overlap(a, b)
    assert compare(outcomes(a), outcomes(b), condition="nominal").p_value == 0.0625


# Holm and tie groups ---------------------------------------------------------------------------


def test_holm_steps_down_until_the_first_p_value_it_keeps() -> None:
    # Thresholds 0.05/4, 0.05/3, 0.05/2, 0.05/1 against the sorted p-values.
    assert holm_rejections([0.01, 0.04, 0.012, 0.03]) == [True, False, True, False]
    assert holm_rejections([0.001, 0.002, 0.003]) == [True, True, True]
    assert holm_rejections([0.03, 0.03]) == [False, False]  # 0.03 > 0.05/2: none
    assert holm_rejections([0.03]) == [True]
    assert holm_rejections([]) == []


def test_tie_groups_split_where_the_corrected_test_separates_neighbours() -> None:
    p = {("a", "b"): 0.001, ("b", "c"): 0.3, ("c", "d"): 0.004, ("d", "e"): 0.04}
    groups = tie_groups(["a", "b", "c", "d", "e"], lambda x, y: p[(x, y)])
    assert groups == [1, 2, 2, 3, 3]  # 0.04 > 0.05/2 after two rejections: d and e share


def test_tie_groups_at_another_level() -> None:
    p = {("a", "b"): 0.001, ("b", "c"): 0.3, ("c", "d"): 0.004, ("d", "e"): 0.04}
    assert tie_groups(["a", "b", "c", "d", "e"], lambda x, y: p[(x, y)], alpha=0.001) == [
        1,
        1,
        1,
        1,
        1,
    ]


def test_tie_groups_of_no_entry_and_of_one() -> None:
    assert tie_groups([], lambda x, y: 0.0) == []
    assert tie_groups(["only"], lambda x, y: 0.0) == [1]


def test_tie_groups_ask_only_for_adjacent_pairs() -> None:
    asked: list[tuple[int, int]] = []

    def p(x: int, y: int) -> float:
        asked.append((x, y))
        return 1.0

    assert tie_groups([1, 2, 3], p) == [1, 1, 1]
    assert asked == [(1, 2), (2, 3)]
