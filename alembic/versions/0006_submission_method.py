"""a submission may name its method and link its paper and code, as leaderboards in the field do

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("method", sa.String(length=100), nullable=True))
        batch_op.add_column(sa.Column("paper_url", sa.String(length=500), nullable=True))
        batch_op.add_column(sa.Column("code_url", sa.String(length=500), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.drop_column("code_url")
        batch_op.drop_column("paper_url")
        batch_op.drop_column("method")
