"""`/help/metrics`: docs/metrics.md, what the numbers mean, as a page of the site, so that a
board can link its tie groups to the rule that draws them ("#paired-significance"). The file is
the project's own (it ships in the image, .dockerignore), rendered once per process, raw HTML
off as everywhere."""

from __future__ import annotations

import functools
import itertools
import re
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import Response
from markdown_it import MarkdownIt
from markupsafe import Markup

from server.accounts.deps import ViewerDep
from server.kit.pages import render

router = APIRouter(include_in_schema=False)

METRICS = Path(__file__).resolve().parents[2] / "docs" / "metrics.md"


def anchor(title: str) -> str:
    """A heading's anchor as GitHub writes it: lower case, punctuation dropped, spaces to -."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


@functools.cache
def metrics_html() -> Markup:
    """docs/metrics.md as HTML, each heading with its anchor as id."""
    md = MarkdownIt("commonmark", {"html": False}).enable("table").disable("image")
    tokens = md.parse(METRICS.read_text())
    for opening, inline in itertools.pairwise(tokens):
        if opening.type == "heading_open":
            opening.attrSet("id", anchor(inline.content))
    return Markup(md.renderer.render(tokens, md.options, {}))  # html off: escaped


@router.get("/help/metrics")
def metrics_page(request: Request, who: ViewerDep) -> Response:
    """What the numbers mean: scores, intervals, the paired test and the tie groups."""
    return render(request, who, "help.html", title="What the numbers mean", body=metrics_html())
