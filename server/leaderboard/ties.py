"""A board's tie groups: neighbours the paired test does not separate share a group
(`evaluator.paired.tie_groups`: McNemar's exact test on the ranked condition's paired episodes,
Holm's correction over all the board's adjacent comparisons; docs/metrics.md, "Paired
significance").

Holm's thresholds depend on every adjacent p-value, so any change to the board may move any
group: the groups are counted again whole on every snapshot. What costs is the tests, and a
test's p-value depends on its two rows alone: it is kept by the rows' serials (which name their
content) and carried from snapshot to snapshot, so a change tests only the pairs it made.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session as DB

from evaluator.paired import Outcome, PackedOutcomes, compare, compare_packed, tie_groups
from server.leaderboard.stored import Stored
from server.models import Submission
from server.standings.entries import packed_outcomes, ranked_outcomes

Pair = tuple[int, int]  # the serials of the row above and the row below


@dataclass(frozen=True)
class TieGroups:
    groups: list[int | None]  # None for baselines: they are not ranked
    tied: list[bool]  # in the same group as the ranked row above
    p_values: dict[Pair, float]  # of the board's adjacent ranked rows


def count_groups(
    db: DB,
    rows: Sequence[Stored],
    ranks: Sequence[int | None],
    *,
    alpha: float,
    known: Mapping[Pair, float],
) -> TieGroups:
    """The groups of the ranked rows, testing only the adjacent pairs `known` lacks."""
    ranked = [s for s, rank in zip(rows, ranks, strict=True) if rank is not None]
    p_values: dict[Pair, float] = {}

    def p_value(above: Stored, below: Stored) -> float:
        pair = (above.serial, below.serial)
        found = known.get(pair)
        p_values[pair] = found if found is not None else paired_p_value(db, above, below)
        return p_values[pair]

    numbers = iter(tie_groups(ranked, p_value, alpha=alpha))
    groups = [None if rank is None else next(numbers) for rank in ranks]
    tied: list[bool] = []
    above: int | None = None
    for group in groups:
        tied.append(group is not None and group == above)
        above = group if group is not None else above
    return TieGroups(groups, tied, p_values)


def paired_p_value(db: DB, above: Stored, below: Stored) -> float:
    """McNemar's exact p-value of two rows' paired episodes: counted on their packed outcomes,
    or, where those ran other seeds, on their episode rows (`evaluator.paired.compare`)."""
    a, b = above.outcomes, below.outcomes
    if a is None or b is None:
        return 1.0  # nothing to pair: nothing separates them
    if a.condition == b.condition and (found := compare_packed(a, b)) is not None:
        return found.p_value
    first, second = _episodes(db, above.submission_id), _episodes(db, below.submission_id)
    return compare(first, second, condition=a.condition).p_value


def outcomes_of(db: DB, entry: Any) -> PackedOutcomes | None:
    """A board row's packed outcomes; for rows stored before rows kept them, read from the
    submission's episodes (until the row is next refreshed)."""
    data = entry.outcomes
    if data is None:
        submission = db.get(Submission, entry.submission_id)
        data = packed_outcomes(db, submission=submission) if submission is not None else None
    return PackedOutcomes.from_json(data) if data is not None else None


def _episodes(db: DB, submission_id: int) -> list[Outcome]:
    submission = db.get(Submission, submission_id)
    found = ranked_outcomes(db, submission=submission) if submission is not None else None
    return found[1] if found is not None else []
