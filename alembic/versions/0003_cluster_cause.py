"""an error the cluster caused has its own cause, so the attempt runs again once

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OLD = ("worker_lost", "worker_restarted")
NEW = (*OLD, "cluster")


def upgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TYPE transition_cause ADD VALUE IF NOT EXISTS 'cluster'")
    # Elsewhere the enum is a plain string column (no CHECK constraint): nothing to change.


def downgrade() -> None:
    # A cluster's error stays counted as a loss, so a submission still runs again only once.
    op.execute("UPDATE transitions SET cause = 'worker_lost' WHERE cause = 'cluster'")
    if op.get_bind().dialect.name != "postgresql":
        return
    op.execute("ALTER TYPE transition_cause RENAME TO transition_cause_old")
    sa.Enum(*OLD, name="transition_cause").create(op.get_bind())
    op.execute(
        "ALTER TABLE transitions ALTER COLUMN cause TYPE transition_cause "
        "USING cause::text::transition_cause"
    )
    op.execute("DROP TYPE transition_cause_old")
