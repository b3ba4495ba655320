"""workers claim attempts by name, lost attempts have a typed cause, success_at_end may be
unmeasured

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

CAUSE = sa.Enum("worker_lost", "worker_restarted", name="transition_cause", length=32)
LOST_REASON = "the worker evaluating it stopped responding%"


def upgrade() -> None:
    CAUSE.create(op.get_bind(), checkfirst=True)
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("worker", sa.String(length=200), nullable=True))
    with op.batch_alter_table("transitions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("cause", CAUSE, nullable=True))
    # Losses recorded before the column existed were told apart by their text; keep counting them.
    op.execute(
        sa.text(
            "UPDATE transitions SET cause = 'worker_lost' "
            "WHERE to_state = 'error' AND reason LIKE :reason"
        ).bindparams(reason=LOST_REASON)
    )
    with op.batch_alter_table("episode_results", schema=None) as batch_op:
        batch_op.alter_column("success_at_end", existing_type=sa.Boolean(), nullable=True)


def downgrade() -> None:
    op.execute(
        "UPDATE episode_results SET success_at_end = success_once WHERE success_at_end IS NULL"
    )
    with op.batch_alter_table("episode_results", schema=None) as batch_op:
        batch_op.alter_column("success_at_end", existing_type=sa.Boolean(), nullable=False)
    with op.batch_alter_table("transitions", schema=None) as batch_op:
        batch_op.drop_column("cause")
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.drop_column("worker")
    CAUSE.drop(op.get_bind(), checkfirst=True)
