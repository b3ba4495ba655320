"""`manieval compare A B`: are two submissions' scores really different?

Both submissions ran the same episodes (same challenge, same phase: the same seeds), so their
outcomes pair up; McNemar's exact test on the pairs of the ranked condition answers
(docs/metrics.md, "Paired significance"). The episode records it needs are readable by their
owner and admins only, so the caller must be allowed to read both.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from manieval import render
from manieval.client import ApiError, Client
from manieval.connect import JsonOption, ServerOption, connect, print_json
from manieval.errors import ExitCode, fail, handled

if TYPE_CHECKING:  # the evaluator is imported when the command runs: `--help` needs none
    from evaluator.paired import Outcome, PairedComparison, PairedTable

JSON = dict[str, Any]
Alpha = Annotated[float, typer.Option(help="The test's level, between 0 and 1.")]


def compare(
    a: Annotated[int, typer.Argument(min=1, metavar="A", help="The first submission's number.")],
    b: Annotated[int, typer.Argument(min=1, metavar="B", help="The second submission's number.")],
    alpha: Alpha = 0.05,
    as_json: JsonOption = False,
    server: ServerOption = None,
) -> None:
    """Compare two of your submissions episode by episode (McNemar's exact test)."""
    if not 0 < alpha < 1:
        raise typer.BadParameter("must lie strictly between 0 and 1", param_hint="--alpha")
    from evaluator.paired import compare as paired

    with handled(), connect(server, login="required") as client:
        first, second = client.submission(a), client.submission(b)
        _check_comparable(first, second)
        challenge = client.challenge(first["challenge"])
        condition = challenge["conditions"][0]["name"]  # the one the board ranks
        found = paired(_outcomes(client, a), _outcomes(client, b), condition=condition)
    order = [t["env_id"] for t in challenge["tasks"]]
    if as_json:
        print_json(_as_json(first, second, found, alpha=alpha, order=order))
        return
    out = render.stdout()
    out.print(_table(a, b, found, order=order))
    out.print(verdict(a, b, found, alpha=alpha))
    if found.unpaired_a or found.unpaired_b:
        render.stderr().print(
            f"not paired: {found.unpaired_a} episodes of {a} and {found.unpaired_b} of {b} "
            "ran seeds the other did not"
        )


def _check_comparable(first: JSON, second: JSON) -> None:
    for s in (first, second):
        if s["state"] != "succeeded":
            fail(
                ExitCode.CONFLICT,
                f"submission {s['id']} ended {s['state']}, not succeeded",
                "only a completed evaluation has every planned episode to pair",
            )
    where = [(s["challenge"], s["phase"]) for s in (first, second)]
    if where[0] != where[1]:
        fail(
            ExitCode.CONFLICT,
            f"submission {first['id']} ran {'/'.join(where[0])} and submission {second['id']} "
            f"ran {'/'.join(where[1])}",
            "only submissions to the same challenge and phase ran the same episodes",
        )


def _outcomes(client: Client, submission_id: int) -> list[Outcome]:
    from evaluator.paired import Outcome

    try:
        episodes = client.episodes(submission_id)
    except ApiError as exc:
        if exc.status != 403:
            raise
        fail(
            ExitCode.FORBIDDEN,
            f"cannot read the episodes of submission {submission_id}: {exc.message}",
            "compare needs both submissions' episode records, which only their owner "
            "(or team) and admins may read",
        )
    return [
        Outcome(e["condition"], e["env_id"], e["index"], e["seed"], e["success_once"])
        for e in episodes
    ]


def _ordered(found: PairedComparison, order: list[str]) -> list[tuple[str, PairedTable]]:
    """The tasks in the suite's order (any the suite no longer lists, after them)."""
    rank = {env_id: i for i, env_id in enumerate(order)}
    return sorted(found.tasks.items(), key=lambda item: rank.get(item[0], len(rank)))


def _table(a: int, b: int, found: PairedComparison, *, order: list[str]) -> Table:
    table = Table(title=f"{a} (A) against {b} (B), condition {found.condition}, paired episodes")
    for column in ("task", "both", "only A", "only B", "neither", "A", "B", "p (exact)"):
        table.add_column(column, justify="left" if column == "task" else "right")
    rows = [*_ordered(found, order), ("pooled", found.pooled)]
    for name, t in rows:
        cells = (t.both, t.only_a, t.only_b, t.neither)
        table.add_row(
            Text(name, style="bold" if name == "pooled" else ""),
            *(str(n) for n in cells),
            f"{t.both + t.only_a}/{t.pairs}",
            f"{t.both + t.only_b}/{t.pairs}",
            f"{t.p_value:.3g}",
        )
    return table


def verdict(a: int, b: int, found: PairedComparison, *, alpha: float) -> str:
    """One line: whether the pooled test separates A and B at `alpha`, and which way."""
    t, p = found.pooled, found.p_value
    if not found.significant(alpha):
        return (
            f"no significant difference at {alpha:g} (p = {p:.3g}, McNemar exact): "
            f"{a} alone solved {t.only_a}, {b} alone {t.only_b} of {t.pairs} paired episodes"
        )
    better, worse = (a, b) if t.only_a > t.only_b else (b, a)
    return (
        f"{better} is better than {worse} at {alpha:g} (p = {p:.3g}, McNemar exact): "
        f"{a} alone solved {t.only_a}, {b} alone {t.only_b} of {t.pairs} paired episodes"
    )


def _as_json(
    first: JSON, second: JSON, found: PairedComparison, *, alpha: float, order: list[str]
) -> JSON:
    def table(t: PairedTable) -> JSON:
        counts = {"both": t.both, "only_a": t.only_a, "only_b": t.only_b, "neither": t.neither}
        return counts | {"p_value": t.p_value}

    return {
        "a": first["id"],
        "b": second["id"],
        "challenge": first["challenge"],
        "phase": first["phase"],
        "condition": found.condition,
        "alpha": alpha,
        "tasks": [{"env_id": name} | table(t) for name, t in _ordered(found, order)],
        "pooled": table(found.pooled),
        "p_value": found.p_value,
        "significant": found.significant(alpha),
        "unpaired_a": found.unpaired_a,
        "unpaired_b": found.unpaired_b,
    }
