"""Audit records as the console shows them: the challenge by its slug, what changed in words."""

from __future__ import annotations

import json
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.models import AuditRecord, Challenge


def challenge_slugs(db: DB) -> dict[int, str]:
    """Every challenge's slug by its id."""
    return dict(db.execute(select(Challenge.id, Challenge.slug)).all())


def shown(record: AuditRecord, slugs: dict[int, str]) -> dict[str, Any]:
    """A record as the console lists it: the challenge by its slug (of `slugs`, by id), what
    changed in words."""
    return {
        "record": record,
        "challenge": slugs.get(record.challenge_id) if record.challenge_id else None,
        "changes": describe(record.detail),
    }


def describe(detail: dict[str, Any] | None) -> list[str]:
    """A record's detail as lines: `name: old → new` for a change of settings, `name: value`
    for anything else."""
    if not detail:
        return []
    old, new = detail.get("old"), detail.get("new")
    lines = [f"{k}: {_value(v)}" for k, v in detail.items() if k not in ("old", "new")]
    if isinstance(old, dict) and isinstance(new, dict):
        lines += [f"{k}: {_value(old.get(k))} → {_value(new.get(k))}" for k in new]
    else:
        lines += [f"{k}: {_value(detail[k])}" for k in ("old", "new") if k in detail]
    return lines


def _value(value: object) -> str:
    return "none" if value is None else value if isinstance(value, str) else json.dumps(value)
