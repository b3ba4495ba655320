import pytest

from evaluator.runner import make_shards
from tests.evaluator.conftest import tiny_plan


def test_shards_cover_every_episode_exactly_once_in_contiguous_chunks():
    plan = tiny_plan(conditions=["nominal"], episodes=5)
    shards = make_shards(plan, 2)
    assert [s.units for s in shards] == [
        ((0, ((0, 100), (1, 101), (2, 102))), (1, ((0, 100), (1, 101), (2, 102)))),
        ((0, ((3, 103), (4, 104))), (1, ((3, 103), (4, 104)))),
    ]


def test_more_workers_than_episodes_leaves_no_empty_shard():
    plan = tiny_plan(tasks=["PickCube-v1"], conditions=["nominal"], episodes=2)
    shards = make_shards(plan, 4)
    assert len(shards) == 2
    assert all(len(s.units) == 1 for s in shards)


def test_zero_workers_is_refused():
    with pytest.raises(ValueError, match="at least 1"):
        make_shards(tiny_plan(), 0)
