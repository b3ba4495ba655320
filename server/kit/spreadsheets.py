"""Text that a spreadsheet opens: the CSV the service writes is read there."""

from __future__ import annotations


def csv_safe(text: str) -> str:
    """Spreadsheets run cells starting with = + - @ as formulas: defuse them."""
    return "'" + text if text[:1] in ("=", "+", "-", "@") else text
