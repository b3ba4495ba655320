"""Rendered leaderboard contents are kept by key, the least recently used going first once
there are too many or they are too large together."""

from __future__ import annotations

from server.leaderboard.rendered import BoardPages


def test_kept_contents_stay_within_their_count_and_size() -> None:
    pages = BoardPages(size=3, budget=10)
    renders: list[str] = []

    def render(text: str) -> str:
        renders.append(text)
        return text

    assert pages.get("a", lambda: render("aaaa")) == "aaaa"
    assert pages.get("a", lambda: render("other")) == "aaaa"  # kept
    pages.get("b", lambda: render("bbbb"))
    pages.get("a", lambda: render("aaaa"))  # a is the most recently used now
    pages.get("c", lambda: render("cccc"))  # 12 characters: b, the least recent, goes
    assert renders == ["aaaa", "bbbb", "cccc"]
    pages.get("b", lambda: render("bbbb"))  # rendered again; a goes (c, b: 8 characters)
    pages.get("c", lambda: render("cccc"))
    assert renders == ["aaaa", "bbbb", "cccc", "bbbb"]
    for key in "def":
        pages.get(key, lambda: render("x"))
    assert pages.get("c", lambda: render("cccc")) == "cccc"
    assert renders[-1] == "cccc"  # three at most: c went for d, e and f
