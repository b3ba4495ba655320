"""tracks: a challenge may be a track of another (its group's head), named within the group;
the head says whether its tracks share one quota

Existing challenges stay alone: no group, their own quota.

Revision ID: 0015
Revises: 0014
Create Date: 2026-11-27
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0015"
down_revision: str | None = "0014"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # In place, never by rebuilding `challenges` on SQLite (see 0012): no foreign key on
    # `track_of`, which SQLite adds only by rebuilding the table.
    op.add_column("challenges", sa.Column("track_of", sa.Integer(), nullable=True))
    op.create_index("ix_challenges_track_of", "challenges", ["track_of"])
    op.add_column("challenges", sa.Column("track", sa.String(length=32), nullable=True))
    op.add_column(
        "challenges",
        sa.Column("quota_shared", sa.Boolean(), nullable=False, server_default=sa.false()),
    )


def downgrade() -> None:
    op.drop_index("ix_challenges_track_of", table_name="challenges")
    for column in ("quota_shared", "track", "track_of"):
        op.drop_column("challenges", column)  # in place (SQLite 3.35 and later), as 0013's
