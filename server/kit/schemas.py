"""What the API's bodies share: the strict base of request bodies, the text types every text
field uses, a page of items, `Ok`.

Text the server stores or renders must be text Postgres and the templates can hold: no NUL
(Postgres refuses it in `text`), no lone surrogate (not encodable as UTF-8), no other C0 control
character (tab, line feed and carriage return only in multi-line text) and not the
non-characters U+FFFE and U+FFFF. `Line` and `Text` refuse them with a 422 and state it in the
OpenAPI document as a `pattern`; `text_problem` is the same check for form fields and the
request guard (`server/kit/limits.py`) applies it to every path and query string.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Generic, TypeVar

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, StrictBool, field_validator

T = TypeVar("T")

# The same sets as a regular expression (for the OpenAPI document, which JSON Schema tools and
# schemathesis read) and as a compiled one (for the check). Written with escapes, so the
# document holds no raw control character.
_LINE_FORBIDDEN = r"\x00-\x1f\ud800-\udfff\ufffe\uffff"
_TEXT_FORBIDDEN = r"\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff"


def line_pattern(also_forbidden: str = "") -> str:
    """The pattern of one line of text, refusing these characters too (a character class)."""
    return rf"^[^{_LINE_FORBIDDEN}{also_forbidden}]*$"


LINE_PATTERN = line_pattern()
"""One line of text: no control character at all."""
TEXT_PATTERN = rf"^[^{_TEXT_FORBIDDEN}]*$"
"""Multi-line text: tab, line feed and carriage return allowed, no other control character."""
_LINE_BAD = re.compile(f"[{_LINE_FORBIDDEN}]")
_TEXT_BAD = re.compile(f"[{_TEXT_FORBIDDEN}]")


def text_problem(value: str, *, multiline: bool = False) -> str | None:
    """Why `value` cannot be stored or shown as text, or None when it can."""
    found = (_TEXT_BAD if multiline else _LINE_BAD).search(value)
    if found is None:
        return None
    return f"contains a character that is not allowed here (U+{ord(found.group()):04X})"


def _line(value: str) -> str:
    if (problem := text_problem(value)) is not None:
        raise ValueError(problem)
    return value


def _text(value: str) -> str:
    if (problem := text_problem(value, multiline=True)) is not None:
        raise ValueError(problem)
    return value


# The pattern is documented only: pydantic's regex engine (Rust) cannot match surrogates, so the
# validator above enforces it.
Line = Annotated[str, AfterValidator(_line), Field(json_schema_extra={"pattern": LINE_PATTERN})]
"""A one-line text field (a name, a login, a reference)."""
Text = Annotated[str, AfterValidator(_text), Field(json_schema_extra={"pattern": TEXT_PATTERN})]
"""A multi-line text field (a description)."""
SLUG_PATTERN = r"^[a-z0-9][a-z0-9_-]*$"
"""A challenge's slug: its suite's name (evaluator/suite.py)."""
Flag = StrictBool
"""A boolean given as JSON `true`/`false` only: `0`, `"no"` or `"false"` are refused."""


def _document_text(schema: dict[str, Any]) -> None:
    # Every text field without a pattern of its own is held to `Text`'s, so the document says
    # what `InBody._storable` enforces.
    for field in schema.get("properties", {}).values():
        variants = field.get("anyOf", [field])
        for variant in variants:
            if variant.get("type") == "string" and "pattern" not in variant:
                variant["pattern"] = TEXT_PATTERN


class InBody(BaseModel):
    """A request body: unknown fields are refused, not ignored; no type is coerced (`0` is no
    boolean, `"1"` no number); and no text field holds what cannot be stored (see `Text`)."""

    model_config = ConfigDict(
        extra="forbid", str_strip_whitespace=False, strict=True, json_schema_extra=_document_text
    )

    @field_validator("*", mode="after")
    @classmethod
    def _storable(cls, value: object) -> object:
        if isinstance(value, str) and (problem := text_problem(value, multiline=True)):
            raise ValueError(problem)
        return value


class Page(BaseModel, Generic[T]):
    items: list[T]
    page: int
    per_page: int
    total: int


class Ok(BaseModel):
    ok: bool = True
