"""challenge rules: per phase, best or last counts, a final choice, a post-deadline board and a
board hidden until published; per submission, its final mark and whether it came late

Existing phases keep what they did: best counts, no final choice, late ones refused, public.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-27
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # In place, never by rebuilding `phases` or `submissions` on SQLite (see 0012); the final
    # choice's uniqueness is a unique index, which SQLite adds in place.
    op.add_column(
        "phases", sa.Column("counts", sa.String(length=8), nullable=False, server_default="best")
    )
    op.add_column(
        "phases", sa.Column("final_choice", sa.Boolean(), nullable=False, server_default=sa.false())
    )
    op.add_column(
        "phases",
        sa.Column("after_close", sa.String(length=16), nullable=False, server_default="refuse"),
    )
    op.add_column(
        "phases", sa.Column("board", sa.String(length=8), nullable=False, server_default="public")
    )
    op.add_column("phases", sa.Column("published_at", sa.DateTime(timezone=True), nullable=True))
    op.add_column(
        "submissions",
        sa.Column("post_deadline", sa.Boolean(), nullable=False, server_default=sa.false()),
    )
    op.add_column("submissions", sa.Column("final_for", sa.String(length=32), nullable=True))
    op.create_index("uq_submissions_final", "submissions", ["phase_id", "final_for"], unique=True)


def downgrade() -> None:
    op.drop_index("uq_submissions_final", table_name="submissions")
    for table, column in (
        ("submissions", "final_for"),
        ("submissions", "post_deadline"),
        ("phases", "published_at"),
        ("phases", "board"),
        ("phases", "after_close"),
        ("phases", "final_choice"),
        ("phases", "counts"),
    ):
        op.drop_column(table, column)  # in place (SQLite 3.35 and later), as 0012's
