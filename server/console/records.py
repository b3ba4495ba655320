"""Audit records as the console shows them: the challenge by its slug, what changed in words."""

from __future__ import annotations

import json
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from server.models import AuditRecord, Challenge, User


def challenge_slugs(db: DB) -> dict[int, str]:
    """Every challenge's slug by its id."""
    return dict(db.execute(select(Challenge.id, Challenge.slug)).all())


def shown(db: DB, records: list[AuditRecord]) -> list[dict[str, Any]]:
    """Records as the console lists them: the challenge by its slug, an account by its name,
    what changed in words."""
    slugs = challenge_slugs(db)
    users = {r.target_id for r in records if r.target_kind == "user" and r.target_id}
    names = dict(db.execute(select(User.id, User.username).where(User.id.in_(users))).all())
    return [
        {
            "record": r,
            "challenge": slugs.get(r.challenge_id) if r.challenge_id else None,
            "user": names.get(r.target_id) if r.target_kind == "user" and r.target_id else None,
            "changes": describe(r.detail),
        }
        for r in records
    ]


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
