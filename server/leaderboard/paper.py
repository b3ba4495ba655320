"""A board as a table for a paper, Markdown or LaTeX: per-task success with its interval, the
score with its interval, the tie groups, and one line of provenance.

Names in it (participants, methods, teams) are anyone's to choose, and the result documents'
fields come from workers: every cell is escaped for the format, so that a name cannot break the
table, run LaTeX commands (`\\input`, `\\write18`) or inject Markdown links or HTML.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.leaderboard.service import Row
from server.leaderboard.snapshot import Snapshot
from server.models import Submission

PaperFormat = Literal["markdown", "latex"]
SUFFIX = {"markdown": "md", "latex": "tex"}
MEDIA_TYPE = {"markdown": "text/markdown; charset=utf-8", "latex": "application/x-latex"}

_MARKDOWN_SPECIAL = re.compile(r"([\\`*_{}\[\]()#+\-.!|<>~&])")
_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "{": r"\{",
    "}": r"\}",
    "$": r"\$",
    "&": r"\&",
    "%": r"\%",
    "#": r"\#",
    "_": r"\_",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
    "<": r"\textless{}",
    ">": r"\textgreater{}",
    "|": r"\textbar{}",
    '"': r"\textquotedbl{}",
}


def _one_line(text: str) -> str:
    """Control characters and line breaks as spaces, runs of space as one."""
    return " ".join("".join(c if c.isprintable() else " " for c in text).split())


def escape_markdown(text: str) -> str:
    """`text` as literal Markdown inside a table cell: every punctuation mark that Markdown
    (CommonMark, GitHub's tables) reads is backslash-escaped, on one line."""
    return _MARKDOWN_SPECIAL.sub(r"\\\1", _one_line(text))


def escape_latex(text: str) -> str:
    """`text` as literal LaTeX text: its ten special characters (and those that T1 lacks)
    replaced by the commands that print them, on one line."""
    return "".join(_LATEX_SPECIAL.get(c, c) for c in _one_line(text))


def provenance(db: DB, *, submission_ids: Iterable[int], alpha: float) -> str:
    """What produced the rows' numbers, in one line of plain text: the suites and versions
    their result documents record (several values where the rows differ), and the rule of
    the tie groups. Everything a result document records of its provenance goes here."""
    result = Submission.result
    found = db.execute(
        select(result["suite"], result["versions"]).where(Submission.id.in_(set(submission_ids)))
    ).all()
    seen: dict[str, list[str]] = {}
    for suite, versions in found:
        parts: dict[str, Any] = {}
        if isinstance(suite, dict):
            sha = str(suite.get("sha256", ""))[:12]
            parts["suite"] = f"{suite.get('name')} v{suite.get('version')} (sha256 {sha})"
        if isinstance(versions, dict):
            parts |= {_PACKAGES.get(str(k), str(k)): v for k, v in versions.items()}
        for name, value in parts.items():
            values = seen.setdefault(name, [])
            if str(value) not in values:
                values.append(str(value))
    shown = [
        f"{name} {' / '.join(values)}" if name != "suite" else f"suite {' / '.join(values)}"
        for name, values in seen.items()
    ]
    rule = f"tie groups: McNemar's exact test, Holm-corrected, at {alpha:g}"
    return "; ".join([*shown, rule])


_PACKAGES = {
    "manieval": "ManiEval",
    "mani_skill": "ManiSkill",
    "sapien": "SAPIEN",
    "torch": "torch",
    "python": "Python",
}


def paper_table(
    board: Snapshot, *, format: PaperFormat, page: int, per_page: int, line: str
) -> str:
    """One page of the board as a Markdown or LaTeX table, `line` (the provenance) under it."""
    start, stop = (page - 1) * per_page, min(page * per_page, board.total)
    rows = [board.row(i) for i in range(start, stop)]
    title = f"{board.slug} leaderboard, phase {board.phase}"
    if format == "markdown":
        return _markdown(rows, board.tasks, title=title, line=line)
    return _latex(rows, board.tasks, title=title, line=line, alpha=board.alpha)


def _rate(value: float, low: float | None, high: float | None) -> str:
    return (
        f"{value:.3f} [{low:.3f}, {high:.3f}]"
        if low is not None and high is not None
        else (f"{value:.3f}")
    )


def _mark(row: Row) -> str:
    if row.disqualified is not None:
        return " (disqualified)"  # the reason is the board's and the submission page's
    return " (baseline)" if row.baseline else ""


def _cells(row: Row, tasks: Sequence[str], escape: Any, *, dash: str) -> list[str]:
    who = row.participant + (f" ({row.method})" if row.method else "")
    found = [
        _rate(t["success_rate"], t.get("ci_low"), t.get("ci_high")) if t else dash
        for t in (row.tasks.get(name) for name in tasks)
    ]
    return [
        dash if row.rank is None else str(row.rank),
        dash if row.tie_group is None else str(row.tie_group),
        escape(who) + _mark(row),
        _rate(row.score, row.score_ci_low, row.score_ci_high),
        *found,
    ]


def _markdown(rows: list[Row], tasks: Sequence[str], *, title: str, line: str) -> str:
    head = ["Rank", "Group", "Participant", "Score [95% CI]", *map(escape_markdown, tasks)]
    lines = [f"**{escape_markdown(title)}**", "", "| " + " | ".join(head) + " |"]
    lines.append("|" + "|".join(["---:", "---:", ":---", *["---:"] * (len(head) - 3)]) + "|")
    lines += ["| " + " | ".join(_cells(r, tasks, escape_markdown, dash="-")) + " |" for r in rows]
    note = (
        "Success rate with its 95% Wilson interval; rows of one tie group are not "
        "significantly different."
    )
    provenance_line = escape_markdown(f"Provenance: {line}")
    return "\n".join([*lines, "", escape_markdown(note), "", provenance_line, ""])


def _latex(rows: list[Row], tasks: Sequence[str], *, title: str, line: str, alpha: float) -> str:
    head = ["Rank", "Group", "Participant", "Score", *map(escape_latex, tasks)]
    caption = (
        f"{escape_latex(title)}: success rate with its 95\\% Wilson interval. Rows of one tie "
        f"group are not significantly different (McNemar's exact test on paired episodes, "
        f"Holm-corrected, $\\alpha = {alpha:g}$)."
    )
    body = [" & ".join(_cells(r, tasks, escape_latex, dash="--")) + r" \\" for r in rows]
    return "\n".join(
        [
            r"\begin{table}[t]",
            r"\centering",
            rf"\caption{{{caption}}}",
            r"\begin{tabular}{rrl" + "r" * (len(head) - 3) + "}",
            r"\hline",
            " & ".join(head) + r" \\",
            r"\hline",
            *body,
            r"\hline",
            r"\end{tabular}",
            rf"\par\smallskip{{\footnotesize Provenance: {escape_latex(line)}.}}",
            r"\end{table}",
            "",
        ]
    )
