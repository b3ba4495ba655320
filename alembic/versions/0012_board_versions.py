"""board versions: a phase's board is re-evaluated into a new version, the previous ones stay
readable; a submission records the version it counts for and the submission it re-evaluates

Everything stored so far is version 1 (docs/server.md, Re-evaluation).

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-28
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _version() -> sa.Column[int]:
    return sa.Column("board_version", sa.Integer(), nullable=False, server_default="1")


def upgrade() -> None:
    # Columns are added in place, never by rebuilding a table on SQLite: dropping the old
    # `phases` or `submissions` there (foreign keys on) would cascade into every table that
    # refers to them. So `reevaluation_of` has no foreign key (a re-evaluation has its
    # original's owner, and goes with them).
    op.add_column("phases", _version())
    op.add_column("phases", sa.Column("pending_board_version", sa.Integer(), nullable=True))
    op.add_column("submissions", _version())
    op.add_column("submissions", sa.Column("reevaluation_of", sa.Integer(), nullable=True))
    op.create_index(
        op.f("ix_submissions_reevaluation_of"), "submissions", ["reevaluation_of"], unique=False
    )
    op.drop_index("ix_leaderboard_rank", table_name="leaderboard_entries")
    with op.batch_alter_table("leaderboard_entries", schema=None) as batch_op:
        batch_op.add_column(_version())
        batch_op.drop_constraint("uq_leaderboard_entries_phase_id", type_="unique")
        batch_op.drop_constraint("uq_leaderboard_entries_phase_team", type_="unique")
        batch_op.create_unique_constraint(
            "uq_leaderboard_entries_phase_id", ["phase_id", "board_version", "owner_key"]
        )
        batch_op.create_unique_constraint(
            "uq_leaderboard_entries_phase_team", ["phase_id", "board_version", "team_id"]
        )
    op.create_index(
        "ix_leaderboard_rank",
        "leaderboard_entries",
        ["phase_id", "board_version", sa.literal_column("score DESC"), "submitted_at", "id"],
        unique=False,
    )


def downgrade() -> None:
    # Only the current version's rows fit the old constraints: the earlier versions' go.
    op.execute(
        "DELETE FROM leaderboard_entries WHERE board_version <> (SELECT phases.board_version "
        "FROM phases WHERE phases.id = leaderboard_entries.phase_id)"
    )
    op.drop_index("ix_leaderboard_rank", table_name="leaderboard_entries")
    with op.batch_alter_table("leaderboard_entries", schema=None) as batch_op:
        batch_op.drop_constraint("uq_leaderboard_entries_phase_team", type_="unique")
        batch_op.drop_constraint("uq_leaderboard_entries_phase_id", type_="unique")
        batch_op.create_unique_constraint(
            "uq_leaderboard_entries_phase_team", ["phase_id", "team_id"]
        )
        batch_op.create_unique_constraint(
            "uq_leaderboard_entries_phase_id", ["phase_id", "owner_key"]
        )
        batch_op.drop_column("board_version")
    op.create_index(
        "ix_leaderboard_rank",
        "leaderboard_entries",
        ["phase_id", sa.literal_column("score DESC"), "submitted_at", "id"],
        unique=False,
    )
    op.drop_index(op.f("ix_submissions_reevaluation_of"), table_name="submissions")
    for table, column in (
        ("submissions", "reevaluation_of"),
        ("submissions", "board_version"),
        ("phases", "pending_board_version"),
        ("phases", "board_version"),
    ):
        op.drop_column(table, column)  # in place (SQLite 3.35 and later): see `upgrade`
