import math
import os
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from fractions import Fraction

import pytest
import redis
from hypothesis import given
from hypothesis import strategies as st

from server.kit.ratelimit import Decision, MemoryRateLimiter, Rate, RateLimiter, RedisRateLimiter

REDIS_URL = "redis://127.0.0.1:6379/0"

# --- Rate ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "rate"),
    [
        ("5/minute", Rate(5, 60.0)),
        ("1/second", Rate(1, 1.0)),
        ("10/seconds", Rate(10, 1.0)),
        ("3/hour", Rate(3, 3600.0)),
        ("100/hours", Rate(100, 3600.0)),
        ("2/day", Rate(2, 86400.0)),
        ("7/days", Rate(7, 86400.0)),
        (" 5 / Minute ", Rate(5, 60.0)),
    ],
)
def test_rate_parse_reads_a_count_per_unit(text: str, rate: Rate):
    assert Rate.parse(text) == rate


@pytest.mark.parametrize(
    "text",
    [
        "",
        "5",
        "/minute",
        "5/",
        "5/fortnight",
        "five/minute",
        "5/minute/hour",
        "-1/minute",
        "1.5/minute",
        "5 per minute",
        "5/minutes!",
        "\u0665/minute",  # an Arabic-Indic digit five
    ],
)
def test_rate_parse_refuses_anything_else_with_a_clear_message(text: str):
    with pytest.raises(ValueError, match=r"^invalid rate .* for example '5/minute'"):
        Rate.parse(text)


def test_rate_parse_refuses_a_zero_count():
    with pytest.raises(ValueError, match="at least 1"):
        Rate.parse("0/minute")


@pytest.mark.parametrize("period", [0.0, -1.0, math.inf, math.nan])
def test_a_rate_needs_a_positive_finite_period(period: float):
    with pytest.raises(ValueError, match="period must be positive"):
        Rate(1, period)


# --- Memory limiter ------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def memory(clock: FakeClock) -> MemoryRateLimiter:
    return MemoryRateLimiter(clock=clock)


def hits(limiter: RateLimiter, key: str, rate: Rate, n: int) -> list[bool]:
    return [limiter.hit(key, rate).allowed for _ in range(n)]


def test_memory_peek_counts_nothing(memory: MemoryRateLimiter):
    rate = Rate(2, 60)
    assert all(memory.peek("k", rate).allowed for _ in range(10))
    assert hits(memory, "k", rate, 2) == [True, True]
    assert memory.peek("k", rate) == Decision(allowed=False, retry_after=30.0)
    assert memory.peek("other", rate).allowed


def test_memory_allows_a_burst_of_limit_hits_then_refuses(memory: MemoryRateLimiter):
    assert hits(memory, "k", Rate(3, 60), 3) == [True, True, True]
    assert memory.hit("k", Rate(3, 60)) == Decision(allowed=False, retry_after=20.0)


def test_memory_allowed_hits_have_no_retry_after(memory: MemoryRateLimiter):
    assert memory.hit("k", Rate(3, 60)) == Decision(allowed=True, retry_after=0.0)


def test_memory_retry_after_shrinks_as_time_passes(memory: MemoryRateLimiter, clock: FakeClock):
    hits(memory, "k", Rate(3, 60), 3)
    clock.advance(5)
    assert memory.hit("k", Rate(3, 60)).retry_after == pytest.approx(15.0)


def test_memory_allows_a_hit_exactly_after_retry_after(memory: MemoryRateLimiter, clock: FakeClock):
    rate = Rate(3, 1)  # an interval of 1/3 s, not exact in binary
    hits(memory, "k", rate, 3)
    for _ in range(50):
        refused = memory.hit("k", rate)
        assert not refused.allowed
        clock.advance(refused.retry_after)
        assert memory.hit("k", rate).allowed


def test_memory_refused_hits_are_not_counted(memory: MemoryRateLimiter, clock: FakeClock):
    hits(memory, "k", Rate(2, 10), 2)
    assert hits(memory, "k", Rate(2, 10), 20) == [False] * 20
    clock.advance(5)
    assert memory.hit("k", Rate(2, 10)).allowed


def test_memory_allows_one_hit_per_interval_after_the_burst(
    memory: MemoryRateLimiter, clock: FakeClock
):
    hits(memory, "k", Rate(4, 60), 4)
    clock.advance(14.9)
    assert not memory.hit("k", Rate(4, 60)).allowed
    clock.advance(0.1)
    assert hits(memory, "k", Rate(4, 60), 2) == [True, False]


def test_memory_refills_the_whole_burst_after_a_period(memory: MemoryRateLimiter, clock: FakeClock):
    hits(memory, "k", Rate(5, 60), 5)
    clock.advance(60)
    assert hits(memory, "k", Rate(5, 60), 6) == [True] * 5 + [False]


def test_memory_keys_are_independent(memory: MemoryRateLimiter):
    hits(memory, "a", Rate(1, 60), 1)
    assert not memory.hit("a", Rate(1, 60)).allowed
    assert memory.hit("b", Rate(1, 60)).allowed


def test_memory_reset_forgets_every_key(memory: MemoryRateLimiter):
    hits(memory, "a", Rate(1, 60), 1)
    memory.reset()
    assert memory.hit("a", Rate(1, 60)).allowed


def test_memory_drops_expired_keys_as_it_grows(memory: MemoryRateLimiter, clock: FakeClock):
    for i in range(3000):
        memory.hit(f"old-{i}", Rate(1, 1))
    clock.advance(2)
    for i in range(1100):
        memory.hit(f"new-{i}", Rate(1, 1))
    assert len(memory) <= 1100


def test_memory_keeps_live_keys_when_it_prunes(memory: MemoryRateLimiter):
    for i in range(5000):
        memory.hit(f"k-{i}", Rate(1, 60))
    assert len(memory) == 5000
    assert not memory.hit("k-0", Rate(1, 60)).allowed


def hammer(limiter: RateLimiter, key: str, rate: Rate, *, threads: int, each: int) -> int:
    """Hit `key` from many threads released at once; return how many hits were allowed."""
    allowed = []
    barrier = threading.Barrier(threads)

    def work() -> None:
        barrier.wait()
        allowed.extend(limiter.hit(key, rate).allowed for _ in range(each))

    workers = [threading.Thread(target=work) for _ in range(threads)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return sum(allowed)


@pytest.fixture
def frequent_thread_switches() -> Iterator[None]:
    """Make the interpreter switch threads every microsecond, so races show up."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    yield
    sys.setswitchinterval(interval)


@pytest.mark.usefixtures("frequent_thread_switches")
def test_memory_allows_exactly_limit_hits_from_many_threads():
    limiter = MemoryRateLimiter()
    assert hammer(limiter, "k", Rate(500, 3600), threads=16, each=100) == 500


class ReferenceBucket:
    """A token bucket in exact arithmetic: the behaviour GCRA must reproduce."""

    def __init__(self, rate: Rate) -> None:
        self.capacity = Fraction(rate.limit)
        self.per_second = Fraction(rate.limit) / Fraction(rate.period_seconds)
        self.tokens: dict[str, Fraction] = {}
        self.seen: dict[str, Fraction] = {}

    def hit(self, key: str, now: Fraction) -> tuple[bool, Fraction]:
        elapsed = now - self.seen.get(key, now)
        tokens = min(self.capacity, self.tokens.get(key, self.capacity) + elapsed * self.per_second)
        self.seen[key] = now
        allowed = tokens >= 1
        self.tokens[key] = tokens - 1 if allowed else tokens
        return allowed, Fraction(0) if allowed else (1 - tokens) / self.per_second


@given(
    limit=st.integers(1, 20),
    period=st.sampled_from([1.0, 2.0, 60.0]),
    steps=st.lists(st.tuples(st.integers(0, 3000), st.sampled_from(["a", "b", "c"])), max_size=60),
)
def test_memory_limiter_matches_a_reference_token_bucket(
    limit: int, period: float, steps: list[tuple[int, str]]
):
    rate = Rate(limit, period)
    clock = FakeClock()
    limiter = MemoryRateLimiter(clock=clock)
    reference = ReferenceBucket(rate)
    elapsed_ms = 0
    for advance_ms, key in steps:
        elapsed_ms += advance_ms
        clock.now = 1000.0 + elapsed_ms / 1000
        decision = limiter.hit(key, rate)
        allowed, retry_after = reference.hit(key, Fraction(elapsed_ms, 1000))
        assert decision.allowed == allowed
        assert decision.retry_after == pytest.approx(float(retry_after), abs=1e-6)


# --- Redis limiter -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def redis_client() -> Iterator[redis.Redis]:
    client = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=1)
    try:
        client.ping()
    except redis.RedisError as exc:
        message = f"Redis is not reachable at {REDIS_URL}: {exc}"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    yield client
    client.close()


@pytest.fixture
def prefix(redis_client: redis.Redis) -> Iterator[str]:
    """A key prefix of this test's own; its keys are deleted afterwards."""
    prefix = f"manieval:test:rl:{uuid.uuid4().hex}:"
    yield prefix
    keys = list(redis_client.scan_iter(match=prefix + "*"))
    if keys:
        redis_client.delete(*keys)


@pytest.fixture
def shared(redis_client: redis.Redis, prefix: str) -> RedisRateLimiter:
    return RedisRateLimiter(redis_client, prefix=prefix)


# Redis counts on its own clock: a bound on a wait it gives is tied to the time measured around
# the calls, never to how fast a machine is (a loaded one takes tenths of a second between two).


def test_redis_allows_a_burst_of_limit_hits_then_refuses(shared: RedisRateLimiter):
    started = time.monotonic()
    assert hits(shared, "k", Rate(3, 60), 3) == [True, True, True]
    refused = shared.hit("k", Rate(3, 60))
    assert not refused.allowed
    assert 20.0 - (time.monotonic() - started) - 0.001 <= refused.retry_after <= 20.0


def test_redis_peek_counts_nothing(shared: RedisRateLimiter):
    rate = Rate(2, 60)
    assert all(shared.peek("k", rate).allowed for _ in range(10))
    started = time.monotonic()
    assert hits(shared, "k", rate, 2) == [True, True]
    refused = shared.peek("k", rate)
    assert not refused.allowed
    assert 30.0 - (time.monotonic() - started) - 0.001 <= refused.retry_after <= 30.0
    assert shared.peek("other", rate).allowed


def test_redis_allowed_hits_have_no_retry_after(shared: RedisRateLimiter):
    assert shared.hit("k", Rate(3, 60)) == Decision(allowed=True, retry_after=0.0)


def test_redis_allows_a_hit_after_waiting_retry_after(shared: RedisRateLimiter):
    rate = Rate(2, 2.0)
    decisions = [shared.hit("k", rate) for _ in range(10)]  # a slow machine refills between some
    refused = next(d for d in decisions if not d.allowed)
    assert 0 < refused.retry_after <= 1.0
    time.sleep(refused.retry_after)
    assert shared.hit("k", rate).allowed


def test_redis_refused_hits_are_not_counted(shared: RedisRateLimiter):
    rate = Rate(1, 3600)
    shared.hit("k", rate)
    refused = [shared.hit("k", rate) for _ in range(10)]
    assert [d.allowed for d in refused] == [False] * 10
    # Counted, each would push the next allowed hit an hour later; not counted, the wait only
    # shrinks as time passes.
    waits = [d.retry_after for d in refused]
    assert waits == sorted(waits, reverse=True)
    assert waits[0] <= 3600


def test_redis_keys_are_independent(shared: RedisRateLimiter):
    shared.hit("a", Rate(1, 60))
    assert not shared.hit("a", Rate(1, 60)).allowed
    assert shared.hit("b", Rate(1, 60)).allowed


def test_redis_keys_expire_when_the_burst_has_refilled(
    shared: RedisRateLimiter, redis_client: redis.Redis, prefix: str
):
    started = time.monotonic()
    hits(shared, "k", Rate(2, 60), 2)
    left = redis_client.pttl(prefix + "k")
    assert 60_000 - (time.monotonic() - started) * 1000 - 1 <= left <= 60_000


def test_redis_limiters_with_one_prefix_share_their_limits(prefix: str):
    one = RedisRateLimiter(redis.Redis.from_url(REDIS_URL), prefix=prefix)
    other = RedisRateLimiter(redis.Redis.from_url(REDIS_URL), prefix=prefix)
    assert one.hit("k", Rate(1, 60)).allowed
    assert not other.hit("k", Rate(1, 60)).allowed


def test_redis_reset_forgets_only_its_own_prefix(redis_client: redis.Redis, prefix: str):
    mine = RedisRateLimiter(redis_client, prefix=prefix + "mine:")
    theirs = RedisRateLimiter(redis_client, prefix=prefix + "theirs:")
    mine.hit("k", Rate(1, 60))
    theirs.hit("k", Rate(1, 60))
    mine.reset()
    assert mine.hit("k", Rate(1, 60)).allowed
    assert not theirs.hit("k", Rate(1, 60)).allowed


def test_redis_allows_exactly_limit_hits_from_many_threads(shared: RedisRateLimiter):
    assert hammer(shared, "k", Rate(25, 3600), threads=8, each=10) == 25
