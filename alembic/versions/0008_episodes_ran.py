"""task results count the episodes that ran; episodes that never ran are no longer stored

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-27
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

NOT_RUN = "the evaluation stopped before it"
"""What the evaluator wrote as the failure of an episode it planned and never ran (0001-0007
stored those as episode rows)."""


def upgrade() -> None:
    # Added NOT NULL with a default rather than made NOT NULL afterwards: on SQLite that would
    # copy the table, and dropping the old one would cascade to every episode row.
    op.add_column(
        "task_results",
        sa.Column("episodes_ran", sa.Integer(), nullable=False, server_default="0"),
    )
    op.execute(
        sa.text("DELETE FROM episode_results WHERE failure = :not_run").bindparams(not_run=NOT_RUN)
    )
    op.execute(
        "UPDATE task_results SET episodes_ran = (SELECT count(*) FROM episode_results e "
        "WHERE e.task_result_id = task_results.id)"
    )
    # The mean steps of a part-run task were over the planned episodes, the never-run at 0.
    op.execute(
        "UPDATE task_results SET mean_steps = COALESCE((SELECT avg(e.steps) "
        "FROM episode_results e WHERE e.task_result_id = task_results.id), 0) "
        "WHERE episodes_ran < episodes"
    )
    if op.get_bind().dialect.name != "sqlite":  # there, the default stays (see above)
        op.alter_column("task_results", "episodes_ran", server_default=None)


def downgrade() -> None:
    # The episodes that never ran are not made again: they held nothing but their seeds.
    # A native DROP COLUMN (SQLite 3.35+), not a copy of the table (see upgrade).
    op.drop_column("task_results", "episodes_ran")
