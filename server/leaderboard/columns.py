"""The columns of a leaderboard table, in the suite's order, grouped as the page heads them."""

from __future__ import annotations

import re
from dataclasses import dataclass

# Where a long name may break across lines: before an inner capital ("Peg|Insertion|Side-v1")
# and after an underscore ("action_|delay"). The text stays whole for copying and reading.
_BREAKS = re.compile(r"(?<=[a-z0-9])(?=[A-Z])|(?<=_)")


@dataclass(frozen=True)
class Column:
    key: str  # the sort key: score, user, submitted, task:<env_id>, cond:<name>
    label: str
    numeric: bool = True
    group: str = ""  # "task" or "condition" for the grouped columns, else ""

    @property
    def parts(self) -> list[str]:
        """The label cut where a narrow column may wrap it (the page joins them with <wbr>)."""
        return [part for part in _BREAKS.split(self.label) if part]


def board_columns(tasks: list[str], stresses: list[str]) -> list[Column]:
    """Participant, score, each task, each stress condition, then when it was submitted."""
    columns = [Column("user", "Participant", numeric=False), Column("score", "Score")]
    columns += [Column(f"task:{t}", t, group="task") for t in tasks]
    columns += [Column(f"cond:{c}", c, group="condition") for c in stresses]
    return [*columns, Column("submitted", "Submitted", numeric=False)]
