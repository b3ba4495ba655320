"""leaderboard rows record the evaluation environment of their result, for the board to mark
those evaluated in another environment than the service's now

No column changes: the environment goes into each row's summary (JSON), as the rows written
from now on hold it. Rows made before have it filled from their submission's result document:
its provenance where it has one (schema 1.2), else what its versions and suite say.

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-27
"""

import re
from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BATCH = 200
COMPARED = (
    "mani_skill",
    "sapien",
    "torch",
    "numpy",
    "sim_backend",
    "render_backend",
    "suite_sha256",
)
"""The fields of an environment (evaluator/provenance.py as of this revision)."""

entries = sa.table(
    "leaderboard_entries",
    sa.column("id", sa.Integer),
    sa.column("submission_id", sa.Integer),
    sa.column("summary", sa.JSON),
)
submissions = sa.table("submissions", sa.column("id", sa.Integer), sa.column("result", sa.JSON))


def recorded_environment(document: dict[str, Any]) -> dict[str, Any]:
    """The environment a stored result document was evaluated in (a copy of
    `evaluator.provenance.recorded_environment` as of this revision)."""
    provenance = document.get("provenance")
    if isinstance(provenance, dict) and isinstance(provenance.get("environment"), dict):
        found = {k: v for k, v in provenance["environment"].items() if k in COMPARED}
        found.update(provenance.get("shard_differences") or {})
        return found
    versions = document.get("versions") or {}
    found = {name: versions.get(name) for name in ("mani_skill", "sapien", "torch")}
    torch = found["torch"]
    found["torch"] = re.sub(r"\+.*$", "", torch) if isinstance(torch, str) else None
    found["suite_sha256"] = (document.get("suite") or {}).get("sha256")
    return {k: v for k, v in found.items() if v not in (None, "unknown")}


def _rewrite(change: Any) -> None:
    """Apply `change(summary, result)` to every row's summary, a batch of rows at a time."""
    bind = op.get_bind()
    ids = bind.execute(sa.select(entries.c.id).order_by(entries.c.id)).scalars().all()
    for start in range(0, len(ids), BATCH):
        rows = bind.execute(
            sa.select(entries.c.id, entries.c.summary, submissions.c.result)
            .join(submissions, submissions.c.id == entries.c.submission_id)
            .where(entries.c.id.in_(ids[start : start + BATCH]))
        ).all()
        for entry_id, summary, result in rows:
            bind.execute(
                entries.update()
                .where(entries.c.id == entry_id)
                .values(summary=change(dict(summary or {}), result or {}))
            )


def upgrade() -> None:
    _rewrite(lambda summary, result: summary | {"environment": recorded_environment(result)})


def downgrade() -> None:
    _rewrite(lambda summary, _result: {k: v for k, v in summary.items() if k != "environment"})
