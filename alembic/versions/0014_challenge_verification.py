"""challenge verification: the suite's verification report and its problems as loaded

Challenges loaded before it have none (null), and show none until loaded again
(docs/verification.md).

Revision ID: 0014
Revises: 0013
Create Date: 2026-11-27
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0014"
down_revision: str | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("challenges", sa.Column("verification", sa.JSON(), nullable=True))


def downgrade() -> None:
    # In place, as 0012: a batch rebuild of `challenges` on SQLite would cascade into phases.
    op.execute("ALTER TABLE challenges DROP COLUMN verification")
