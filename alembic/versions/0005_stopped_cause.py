"""an attempt the service's own stop interrupted has its own cause: it runs again every time

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OLD = ("worker_lost", "worker_restarted", "cluster")


def upgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TYPE transition_cause ADD VALUE IF NOT EXISTS 'stopped'")
    # Elsewhere the enum is a plain string column (no CHECK constraint): nothing to change.


def downgrade() -> None:
    # Before this revision a stop was told apart from a restart by nothing: it counted as one.
    op.execute("UPDATE transitions SET cause = 'worker_restarted' WHERE cause = 'stopped'")
    if op.get_bind().dialect.name != "postgresql":
        return
    op.execute("ALTER TYPE transition_cause RENAME TO transition_cause_old")
    sa.Enum(*OLD, name="transition_cause").create(op.get_bind())
    op.execute(
        "ALTER TABLE transitions ALTER COLUMN cause TYPE transition_cause "
        "USING cause::text::transition_cause"
    )
    op.execute("DROP TYPE transition_cause_old")
