"""What a submission may say of its method: a name, and links to its paper and code, which the
leaderboard and the submission page show.

The links are shown to everyone as `<a href>`: only absolute `http` and `https` URLs with a
host are kept, so no `javascript:` or `data:` link can reach a page.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from urllib.parse import urlsplit

from server.kit.errors import Invalid
from server.kit.schemas import line_pattern, text_problem

METHOD_MAX = 100
URL_MAX = 500
_BIDI_RANGES = r"\u202a-\u202e\u2066-\u2069"  # escaped: the document holds no raw control
_BIDI = re.compile(f"[{_BIDI_RANGES}]")
"""Directional embeddings, overrides and isolates: in a name shown inside a board's cell or a
CSV line they would reorder what follows it."""
METHOD_PATTERN = line_pattern(_BIDI_RANGES)
"""One line of text without direction controls: what `Method.checked` keeps (documented)."""
URL_PATTERN = r"^$|^https?://[^\s/?#]+[^\s]*$"
"""An absolute http(s) URL with a host, or empty (no link); what `link_problem` checks."""


def link_problem(url: str) -> str | None:
    """Why `url` cannot be shown as a link, or None when it can (empty: no link)."""
    if url == "":
        return None
    if len(url) > URL_MAX:
        return f"at most {URL_MAX} characters"
    if (problem := text_problem(url)) is not None or any(c.isspace() for c in url):
        return problem or "a URL has no spaces"
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - raises on a port that is not a number
    except ValueError:
        return "not a URL"
    if not url.startswith(("http://", "https://")) or not parts.hostname:
        return "an absolute http:// or https:// URL"  # lower case, as the API's pattern says
    return None


@dataclass(frozen=True)
class Method:
    """A submission's method; None in a field of an edit leaves it as it is, "" clears it."""

    name: str | None = None
    paper_url: str | None = None
    code_url: str | None = None

    def checked(self) -> Method:
        """The same, stripped, or `Invalid` naming each field that cannot be kept."""
        fields: dict[str, str] = {}
        name = None if self.name is None else self.name.strip()
        if name is not None and (problem := text_problem(name)):
            fields["method"] = problem
        elif name is not None and _BIDI.search(name):
            fields["method"] = "contains a text direction control (U+202A-U+202E, U+2066-U+2069)"
        elif name is not None and len(name) > METHOD_MAX:
            fields["method"] = f"at most {METHOD_MAX} characters"
        links = {}
        for field in ("paper_url", "code_url"):
            url = getattr(self, field)
            url = None if url is None else url.strip()
            if url is not None and (problem := link_problem(url)):
                fields[field] = problem
            links[field] = url
        if fields:
            raise Invalid("the method's name or links cannot be kept", fields=fields)
        return Method(name=name, **links)

    def stored(self) -> dict[str, str | None]:
        """The columns an edit changes: a field given as "" becomes NULL, None is left out."""
        values = {"method": self.name, "paper_url": self.paper_url, "code_url": self.code_url}
        return {k: (v or None) for k, v in values.items() if v is not None}
