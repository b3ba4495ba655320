"""Rate limits with the generic cell rate algorithm (GCRA), in memory or shared through Redis.

GCRA keeps one number per key, the theoretical arrival time (TAT): when the key's "bucket" will be
empty again. A rate of `limit` per `period` allows a burst of `limit` hits, then one hit every
`period / limit`. Use one key with one rate only, and name the purpose in the key
(`"login:ip:203.0.113.7"`), since the stored TAT means nothing under another rate.
"""

from __future__ import annotations

import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:  # only the type: the memory limiter works without the redis package
    import redis

_UNITS = {"second": 1.0, "minute": 60.0, "hour": 3600.0, "day": 86400.0}
_RATE = re.compile(r"\s*([0-9]+)\s*/\s*(second|minute|hour|day)s?\s*", re.IGNORECASE)


@dataclass(frozen=True)
class Rate:
    """A burst of at most `limit` hits, refilled evenly over `period_seconds`."""

    limit: int
    period_seconds: float

    def __post_init__(self) -> None:
        if self.limit < 1:
            raise ValueError(f"a rate's limit must be at least 1, not {self.limit}")
        if not (math.isfinite(self.period_seconds) and self.period_seconds > 0):
            raise ValueError(f"a rate's period must be positive, not {self.period_seconds}")

    @classmethod
    def parse(cls, text: str) -> Rate:
        """Read `"5/minute"`: a count, then second, minute, hour or day (plural allowed)."""
        match = _RATE.fullmatch(text)
        if match is None:
            raise ValueError(
                f"invalid rate {text!r}: expected '<count>/<unit>' with unit second, minute, "
                "hour or day, for example '5/minute' or '100/hours'"
            )
        return cls(int(match[1]), _UNITS[match[2].lower()])

    @staticmethod
    def checked(text: object) -> object:
        """`text` unchanged when it is a valid rate, else ValueError (a settings validator)."""
        if isinstance(text, str):
            Rate.parse(text)
        return text

    @property
    def interval(self) -> float:
        """Seconds between two hits once the burst is spent."""
        return self.period_seconds / self.limit


@dataclass(frozen=True)
class Decision:
    """Whether a hit is allowed and, when not, the seconds until the next one would be (else 0)."""

    allowed: bool
    retry_after: float


class RateLimiter(Protocol):
    """What the API needs from a limiter: `MemoryRateLimiter` or `RedisRateLimiter`."""

    def hit(self, key: str, rate: Rate) -> Decision:
        """Count one hit on `key` if `rate` allows it (a refused hit is not counted)."""
        ...

    def peek(self, key: str, rate: Rate) -> Decision:
        """Whether a hit on `key` would be allowed now, without counting one."""
        ...

    def reset(self) -> None:
        """Forget every key."""
        ...


# A hit up to a microsecond early is allowed: the TAT is a float sum of `period / limit` steps,
# and without this a hit landing exactly on time could be refused by a rounding error.
_TOLERANCE_SECONDS = 1e-6


def _gcra(tat: float | None, now: float, rate: Rate) -> tuple[Decision, float | None]:
    """The decision for a hit at `now`, and the key's new TAT (None when refused)."""
    new_tat = max(now if tat is None else tat, now) + rate.interval
    wait = new_tat - rate.period_seconds - now
    if wait > _TOLERANCE_SECONDS:
        return Decision(allowed=False, retry_after=wait), None
    return Decision(allowed=True, retry_after=0.0), new_tat


_PRUNE_AT_LEAST = 1024


class MemoryRateLimiter:
    """GCRA in this process, thread-safe: for a single API process, development and tests."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._tats: dict[str, float] = {}
        self._prune_at = _PRUNE_AT_LEAST

    def hit(self, key: str, rate: Rate) -> Decision:
        """Count one hit on `key` if `rate` allows it (a refused hit is not counted)."""
        with self._lock:
            now = self._clock()
            decision, tat = _gcra(self._tats.get(key), now, rate)
            if tat is not None:
                self._tats[key] = tat
                if len(self._tats) >= self._prune_at:
                    self._prune(now)
            return decision

    def peek(self, key: str, rate: Rate) -> Decision:
        """Whether a hit on `key` would be allowed now, without counting one."""
        with self._lock:
            decision, _ = _gcra(self._tats.get(key), self._clock(), rate)
            return decision

    def _prune(self, now: float) -> None:
        # A key whose TAT has passed behaves exactly like a key never seen, so it can go. Pruning
        # when the table has doubled keeps memory within twice the live keys, at O(1) per hit.
        self._tats = {key: tat for key, tat in self._tats.items() if tat > now}
        self._prune_at = max(_PRUNE_AT_LEAST, 2 * len(self._tats))

    def reset(self) -> None:
        """Forget every key."""
        with self._lock:
            self._tats.clear()
            self._prune_at = _PRUNE_AT_LEAST

    def __len__(self) -> int:
        """How many keys are stored (expired ones linger until the next prune)."""
        return len(self._tats)


# Times in microseconds on the Redis server's clock, so API processes on several hosts agree.
# A number passed to redis.call would be formatted with 14 significant digits, too few for
# microseconds since 1970, hence the explicit %.17g. Returns {1, 0} when allowed and
# {0, microseconds to wait} when refused; the key expires when its TAT passes. With ARGV[3] = 1
# only the decision is returned and nothing is stored (a peek).
_GCRA_LUA = """
local limit = tonumber(ARGV[1])
local period = tonumber(ARGV[2])
local dry = ARGV[3] == '1'
local clock = redis.call('TIME')
local now = tonumber(clock[1]) * 1000000 + tonumber(clock[2])
local tat = tonumber(redis.call('GET', KEYS[1]) or now)
if tat < now then tat = now end
local new_tat = tat + period / limit
local wait = new_tat - period - now
if wait > 1 then
  return {0, math.ceil(wait)}
end
if dry then return {1, 0} end
local ttl = string.format('%d', math.ceil((new_tat - now) / 1000))
redis.call('SET', KEYS[1], string.format('%.17g', new_tat), 'PX', ttl)
return {1, 0}
"""

_GLOB_SPECIAL = re.compile(r"([*?\[\]\\])")


class RedisRateLimiter:
    """GCRA in Redis, one atomic script per hit: limits shared by every API process."""

    def __init__(self, client: redis.Redis, prefix: str = "manieval:rl:") -> None:
        self._client = client
        self._prefix = prefix
        self._script = client.register_script(_GCRA_LUA)

    def hit(self, key: str, rate: Rate) -> Decision:
        """Count one hit on `key` if `rate` allows it; Redis errors propagate to the caller."""
        return self._run(key, rate, dry=False)

    def peek(self, key: str, rate: Rate) -> Decision:
        """Whether a hit on `key` would be allowed now, without counting one."""
        return self._run(key, rate, dry=True)

    def _run(self, key: str, rate: Rate, *, dry: bool) -> Decision:
        allowed, wait_us = self._script(
            keys=[self._prefix + key],
            args=[rate.limit, rate.period_seconds * 1_000_000, "1" if dry else "0"],
        )
        return Decision(allowed=bool(allowed), retry_after=int(wait_us) / 1_000_000)

    def reset(self) -> None:
        """Forget every key under this limiter's prefix (a SCAN: for tests and operators)."""
        pattern = _GLOB_SPECIAL.sub(r"\\\1", self._prefix) + "*"
        keys = list(self._client.scan_iter(match=pattern, count=1000))
        for start in range(0, len(keys), 1000):
            self._client.delete(*keys[start : start + 1000])
