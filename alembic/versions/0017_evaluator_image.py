"""a challenge may name its own evaluator image (one with its suite's task packages); an
attempt the operator's configuration cannot run has its own cause

Existing challenges name none: the workers' own evaluator image runs them, as before.

Revision ID: 0017
Revises: 0016
Create Date: 2026-11-27
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0017"
down_revision: str | None = "0016"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OLD = ("worker_lost", "worker_restarted", "cluster", "stopped")


def upgrade() -> None:
    # In place, never by rebuilding `challenges` on SQLite (see 0012 and 0015).
    op.add_column("challenges", sa.Column("evaluator_image", sa.String(512), nullable=True))
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TYPE transition_cause ADD VALUE IF NOT EXISTS 'configuration'")
    # Elsewhere the enum is a plain string column (no CHECK constraint): nothing to change.


def downgrade() -> None:
    # Before this revision such an end had no cause: an `error` of ours, not run again.
    op.execute("UPDATE transitions SET cause = NULL WHERE cause = 'configuration'")
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TYPE transition_cause RENAME TO transition_cause_old")
        sa.Enum(*OLD, name="transition_cause").create(op.get_bind())
        op.execute(
            "ALTER TABLE transitions ALTER COLUMN cause TYPE transition_cause "
            "USING cause::text::transition_cause"
        )
        op.execute("DROP TYPE transition_cause_old")
    op.drop_column("challenges", "evaluator_image")  # in place (SQLite 3.35 and later), as 0013's
