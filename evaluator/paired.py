"""Paired comparison of two evaluations on the same episodes, and tie groups on a ranking.

Every submission to a phase runs the same seeds (`suite.phase_seeds`: a task's seed depends on
the phase, the task and the episode's index only), so two submissions' outcomes pair up episode
by episode. docs/metrics.md, "Paired significance", says why McNemar's exact test and why Holm.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any, TypeVar

from evaluator.stats import mcnemar_exact_p

ALPHA = 0.05
T = TypeVar("T")


@dataclass(frozen=True)
class Outcome:
    """One episode's success (`success_once`, what the score counts) and where it ran."""

    condition: str
    env_id: str
    index: int
    seed: int | None  # None where the phase's seeds are secret: the index fixes it then
    success: bool

    @property
    def key(self) -> tuple[str, str, int, int | None]:
        return self.condition, self.env_id, self.index, self.seed


@dataclass(frozen=True)
class PairedTable:
    """The 2x2 table of paired outcomes: both succeeded, only A, only B, neither."""

    both: int = 0
    only_a: int = 0
    only_b: int = 0
    neither: int = 0

    @property
    def pairs(self) -> int:
        return self.both + self.only_a + self.only_b + self.neither

    @property
    def p_value(self) -> float:
        """McNemar's exact two-sided p-value: only the discordant pairs carry evidence."""
        return mcnemar_exact_p(self.only_a, self.only_b)

    def __add__(self, other: PairedTable) -> PairedTable:
        return PairedTable(
            self.both + other.both,
            self.only_a + other.only_a,
            self.only_b + other.only_b,
            self.neither + other.neither,
        )

    def count(self, a: bool, b: bool) -> PairedTable:
        """This table with one more pair whose outcomes are `a` and `b`."""
        return self + PairedTable(
            int(a and b), int(a and not b), int(b and not a), int(not (a or b))
        )


@dataclass(frozen=True)
class PairedComparison:
    """A against B on one condition: a table per task (in the order first seen) and pooled."""

    condition: str
    tasks: dict[str, PairedTable]
    unpaired_a: int = 0  # episodes of A with no counterpart in B (and the other way round)
    unpaired_b: int = 0
    pooled: PairedTable = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "pooled", sum(self.tasks.values(), PairedTable()))

    @property
    def p_value(self) -> float:
        """The pooled table's p-value: the test of the difference in the condition's score."""
        return self.pooled.p_value

    def significant(self, alpha: float = ALPHA) -> bool:
        return self.p_value <= alpha


def compare(a: Iterable[Outcome], b: Iterable[Outcome], *, condition: str) -> PairedComparison:
    """Pair A's and B's episodes of `condition` by (task, index, seed) and count the tables.

    The suite's score is its first condition's mean over tasks, so that is the condition to
    pass to test a difference in score.
    """
    of_b = _by_key(b, condition=condition, side="B")
    tasks: dict[str, PairedTable] = {}
    of_a = _by_key(a, condition=condition, side="A")
    for key, success in of_a.items():
        if key in of_b:
            env_id = key[1]
            tasks[env_id] = tasks.get(env_id, PairedTable()).count(success, of_b[key])
    return PairedComparison(
        condition=condition,
        tasks=tasks,
        unpaired_a=len(of_a.keys() - of_b.keys()),
        unpaired_b=len(of_b.keys() - of_a.keys()),
    )


def _by_key(
    outcomes: Iterable[Outcome], *, condition: str, side: str
) -> dict[tuple[str, str, int, int | None], bool]:
    found: dict[tuple[str, str, int, int | None], bool] = {}
    for o in outcomes:
        if o.condition != condition:
            continue
        if o.key in found:
            raise ValueError(f"episode {o.key} of {side} is listed twice")
        found[o.key] = o.success
    return found


@dataclass(frozen=True)
class PackedTask:
    """One task's outcomes of one condition, packed: which (index, seed) keys ran (`keys`, a
    digest) and which of them succeeded (bit `index` of `successes`)."""

    keys: str
    count: int
    successes: int


@dataclass(frozen=True)
class PackedOutcomes:
    """An evaluation's outcomes of one condition, packed to compare many pairs fast (a board's
    neighbours): what `compare` counts, as bit counts, when both ran the same keys per task."""

    condition: str
    tasks: dict[str, PackedTask]

    @classmethod
    def of(cls, outcomes: Iterable[Outcome], *, condition: str) -> PackedOutcomes:
        """`outcomes`' episodes of `condition`, packed per task (in the order first seen)."""
        by_task: dict[str, dict[int, tuple[int | None, bool]]] = {}
        for key, success in _by_key(outcomes, condition=condition, side="the run").items():
            _, env_id, index, seed = key
            if index < 0:
                raise ValueError(f"episode {key} has a negative index")
            found = by_task.setdefault(env_id, {})
            if index in found:
                raise ValueError(f"episode {env_id} {index} is listed twice, with two seeds")
            found[index] = (seed, success)
        tasks = {
            env_id: PackedTask(
                keys=_digest(sorted((i, seed) for i, (seed, _) in found.items())),
                count=len(found),
                successes=sum(1 << i for i, (_, ok) in found.items() if ok),
            )
            for env_id, found in by_task.items()
        }
        return cls(condition=condition, tasks=tasks)

    def as_json(self) -> dict[str, Any]:
        """A form that JSON keeps exactly (the bit mask as hex: it may exceed 2^53)."""
        tasks = [[name, t.keys, t.count, f"{t.successes:x}"] for name, t in self.tasks.items()]
        return {"condition": self.condition, "tasks": tasks}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> PackedOutcomes:
        tasks = {
            str(name): PackedTask(str(keys), int(count), int(str(successes), 16))
            for name, keys, count, successes in data["tasks"]
        }
        return cls(condition=str(data["condition"]), tasks=tasks)


def _digest(keys: list[tuple[int, int | None]]) -> str:
    text = ";".join(f"{index}:{seed}" for index, seed in keys)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def compare_packed(a: PackedOutcomes, b: PackedOutcomes) -> PairedComparison | None:
    """`compare` of the outcomes `a` and `b` were packed from, counted on their bits; None when
    a task both ran has keys that differ (the seeds changed): compare the outcomes then."""
    if a.condition != b.condition:
        raise ValueError(f"cannot pair condition {a.condition!r} with {b.condition!r}")
    tasks: dict[str, PairedTable] = {}
    unpaired_a = 0
    for env_id, ta in a.tasks.items():
        if (tb := b.tasks.get(env_id)) is None:
            unpaired_a += ta.count
            continue
        if ta.keys != tb.keys:
            return None
        both = (ta.successes & tb.successes).bit_count()
        only_a = (ta.successes & ~tb.successes).bit_count()
        only_b = (tb.successes & ~ta.successes).bit_count()
        tasks[env_id] = PairedTable(both, only_a, only_b, ta.count - both - only_a - only_b)
    unpaired_b = sum(t.count for name, t in b.tasks.items() if name not in a.tasks)
    return PairedComparison(a.condition, tasks, unpaired_a=unpaired_a, unpaired_b=unpaired_b)


def holm_rejections(p_values: Sequence[float], *, alpha: float = ALPHA) -> list[bool]:
    """Which hypotheses Holm's step-down procedure rejects at family-wise level `alpha`."""
    order = sorted(range(len(p_values)), key=lambda i: p_values[i])
    rejected = [False] * len(p_values)
    for step, i in enumerate(order):
        if p_values[i] > alpha / (len(p_values) - step):
            break
        rejected[i] = True
    return rejected


def tie_groups(
    ranked: Sequence[T], p_value: Callable[[T, T], float], *, alpha: float = ALPHA
) -> list[int]:
    """Group numbers (1, 2, ...) for entries in rank order: an entry starts a new group when
    the difference from the one above it is significant after Holm's correction over all the
    adjacent comparisons; otherwise it shares the group above."""
    adjacent = [p_value(above, below) for above, below in pairwise(ranked)]
    groups = [1] if ranked else []
    for separated in holm_rejections(adjacent, alpha=alpha):
        groups.append(groups[-1] + int(separated))
    return groups
