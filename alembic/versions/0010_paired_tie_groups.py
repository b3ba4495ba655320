"""boards' tie groups are paired: each phase's significance level, each row's packed outcomes

Rows stored before have no outcomes: the board reads them from the episode rows until the row
is next refreshed (server/leaderboard/snapshot.py).

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-02
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # NOT NULL with a default (no table copy on SQLite, see 0008); the level is the suite's
    # default, which every suite had while there was no setting.
    op.add_column(
        "phases",
        sa.Column("significance_level", sa.Float(), nullable=False, server_default="0.05"),
    )
    op.add_column("leaderboard_entries", sa.Column("outcomes", sa.JSON(), nullable=True))
    if op.get_bind().dialect.name != "sqlite":
        op.alter_column("phases", "significance_level", server_default=None)


def downgrade() -> None:
    op.drop_column("leaderboard_entries", "outcomes")
    op.drop_column("phases", "significance_level")
