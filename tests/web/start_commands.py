"""The getting-started page's commands as a participant copies them: each `pre[data-step]`
block, in the page's order, with what it needs beyond the slim install."""

from __future__ import annotations

from dataclasses import dataclass
from html.parser import HTMLParser


@dataclass(frozen=True)
class Block:
    step: str
    needs: str | None
    lines: list[str]


class _Blocks(HTMLParser):
    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.blocks: list[Block] = []
        self._open: tuple[str, str | None] | None = None
        self._text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        found = dict(attrs)
        if tag == "pre" and found.get("data-step"):
            self._open = (str(found["data-step"]), found.get("data-needs"))
            self._text = []

    def handle_data(self, data: str) -> None:
        if self._open is not None:
            self._text.append(data)

    def handle_endtag(self, tag: str) -> None:
        if tag == "pre" and self._open is not None:
            lines = [line for line in "".join(self._text).splitlines() if line.strip()]
            self.blocks.append(Block(self._open[0], self._open[1], lines))
            self._open = None


def page_commands(html: str) -> list[Block]:
    """The command blocks of a getting-started page, in order."""
    parser = _Blocks()
    parser.feed(html)
    return parser.blocks
