"""A board as a table for a paper (Markdown, LaTeX): the rows, intervals, tie groups and the
provenance line, with every name escaped: names are anyone's to choose."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient
from hypothesis import given
from hypothesis import strategies as st
from markdown_it import MarkdownIt
from sqlalchemy.orm import Session

from server.leaderboard.paper import escape_latex, escape_markdown
from server.models import Challenge
from testkit.factories import make_challenge, make_user
from tests.web.helpers import finished

BOARD = "/api/v1/challenges/server-tiny/leaderboard?phase=dev&format="
NASTY = [
    r"\input{/etc/passwd}\write18{rm -rf ~} $x^2$ & 100% #1 a_b {c} ~",
    "[click](javascript:alert(1)) ![i](x.png) <img src=x onerror=alert(1)> **bold** `code`",
    "| cell | break |\n# heading\n- item\r\n1. list &amp; <b>",
    "\x1b[31mred\x00 \\| \\\\ end\\",
]


@pytest.fixture
def tiny(db: Session) -> Challenge:
    return make_challenge(db)


_MD = MarkdownIt("commonmark", {"html": False}).enable("table")


def _cell_text(markdown: str) -> str:
    """The text of the one cell of a table whose cell is `markdown`, as a renderer reads it."""
    tokens = _md_tokens(f"| h |\n|---|\n| {markdown} |\n")
    cells = [t for t in tokens if t.type == "inline"]
    children = cells[1].children or []
    assert {c.type for c in children} <= {"text"}, children  # no link, image, code, html
    return "".join(c.content for c in children)


def _md_tokens(text: str) -> list:  # type: ignore[type-arg]
    return _MD.parse(text)


@pytest.mark.parametrize("name", NASTY)
def test_markdown_cells_read_back_as_the_names_text_and_nothing_else(name: str) -> None:
    assert _cell_text(escape_markdown(name)) == " ".join(
        "".join(c if c.isprintable() else " " for c in name).split()
    )


@given(st.text(max_size=60))
def test_any_name_is_one_plain_markdown_cell(name: str) -> None:
    escaped = escape_markdown(name)
    assert "\n" not in escaped
    _cell_text(escaped)


_LATEX_COMMANDS = re.compile(r"\\(?:text[a-z]+\{\}|[{}$&%#_])")


@pytest.mark.parametrize("name", NASTY)
def test_latex_text_has_no_special_character_left(name: str) -> None:
    escaped = escape_latex(name)
    bare = _LATEX_COMMANDS.sub("", escaped)
    assert not set(bare) & set("\\{}$&%#_~^<>|\n\x1b\x00"), bare
    assert "\\input" not in escaped
    assert "\\write18" not in escaped


@given(st.text(max_size=60))
def test_any_name_is_inert_latex(name: str) -> None:
    bare = _LATEX_COMMANDS.sub("", escape_latex(name))
    assert not set(bare) & set("\\{}$&%#_~^\n")


def test_the_board_as_markdown_and_latex_with_groups_intervals_and_provenance(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    worse = [i < 50 for i in range(100)]
    better = [i < 65 for i in range(100)]
    s = finished(db, make_user(db, "alice"), tiny, better)
    s.method = NASTY[0]
    db.commit()
    from server.standings.entries import refresh

    refresh(db, phase_id=s.phase_id, user_id=s.user_id)
    db.commit()
    finished(db, make_user(db, "bob"), tiny, worse)

    r = client.get(BOARD + "markdown")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/markdown")
    assert 'filename="server-tiny-dev.md"' in r.headers["content-disposition"]
    lines = r.text.splitlines()
    assert lines[2] == "| Rank | Group | Participant | Score [95% CI] | PickCube\\-v1 |"
    who = escape_markdown(f"alice ({NASTY[0]})")
    assert lines[4] == f"| 1 | 1 | {who} | 0.650 [0.553, 0.736] | 0.650 [0.553, 0.736] |"
    assert lines[5] == "| 2 | 2 | bob | 0.500 [0.404, 0.596] | 0.500 [0.404, 0.596] |"
    assert "\nProvenance: suite server\\-tiny v1 \\(sha256 " in r.text
    assert "ManiEval 0; ManiSkill 0; SAPIEN 0; torch 0; Python 3" in r.text

    r = client.get(BOARD + "latex")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("application/x-latex")
    tex = r.text
    assert "\\begin{tabular}{rrlrr}" in tex
    assert f"1 & 1 & {escape_latex(f'alice ({NASTY[0]})')} & 0.650 [0.553, 0.736]" in tex
    assert "\\input{" not in tex
    assert "\\write18" not in tex
    assert "$\\alpha = 0.05$" in tex
    assert "Provenance: suite server-tiny v1 (sha256 " in tex
    assert client.get(BOARD + "pdf").status_code == 422


def test_the_board_page_offers_the_paper_tables(
    client: TestClient, db: Session, tiny: Challenge
) -> None:
    finished(db, make_user(db, "alice"), tiny, [True, False])
    html = client.get("/challenges/server-tiny/leaderboard?phase=dev").text
    assert "format=markdown" in html
    assert "format=latex" in html
