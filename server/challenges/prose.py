"""Challenge and phase descriptions as safe HTML: CommonMark without raw HTML.

Descriptions come from suite files, which an operator loads but anyone may have written, so
markup in them is escaped (markdown-it's `html` option off), links go only to the schemes
markdown-it allows (no `javascript:`), and images are not embedded (the pages' CSP would refuse
other hosts' pictures): their text becomes a link.
"""

from __future__ import annotations

from markdown_it import MarkdownIt
from markdown_it.renderer import RendererHTML
from markdown_it.token import Token
from markdown_it.utils import EnvType, OptionsDict
from markupsafe import Markup

_md = MarkdownIt("commonmark", {"html": False}).disable("image")


def _link_open(
    self: RendererHTML, tokens: list[Token], idx: int, options: OptionsDict, env: EnvType
) -> str:
    tokens[idx].attrSet("rel", "nofollow noopener")
    return self.renderToken(tokens, idx, options, env)


_md.add_render_rule("link_open", _link_open)


def markdown(text: str) -> Markup:
    """`text` (Markdown: paragraphs, `code`, emphasis, lists, links) as HTML blocks."""
    return Markup(_md.render(text))  # markdown-it has escaped the text: html is off


def markdown_inline(text: str) -> Markup:
    """One line of Markdown as inline HTML (no paragraph around it)."""
    return Markup(_md.renderInline(text))


def summary(text: str) -> Markup:
    """The first paragraph of a description, for a card that lists many challenges."""
    first = text.strip().split("\n\n", 1)[0]
    return markdown_inline(" ".join(first.split()))
