"""teams: members, invitations, a challenge's team mode, a submission's team; leaderboard rows
keep a team and the submission's method, paper and code links

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "teams",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=32), nullable=False),
        sa.Column("display_name", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("dissolved_at", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_teams")),
        sa.UniqueConstraint("name", name=op.f("uq_teams_name")),
    )
    op.create_table(
        "team_members",
        sa.Column("user_id", sa.Integer(), nullable=False),
        sa.Column("team_id", sa.Integer(), nullable=False),
        sa.Column("is_admin", sa.Boolean(), nullable=False),
        sa.Column("joined_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["team_id"],
            ["teams.id"],
            name=op.f("fk_team_members_team_id_teams"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["user_id"],
            ["users.id"],
            name=op.f("fk_team_members_user_id_users"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("user_id", name=op.f("pk_team_members")),
    )
    op.create_index(op.f("ix_team_members_team_id"), "team_members", ["team_id"], unique=False)
    op.create_table(
        "team_invitations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("team_id", sa.Integer(), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=False),
        sa.Column("invited_by_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["invited_by_id"],
            ["users.id"],
            name=op.f("fk_team_invitations_invited_by_id_users"),
            ondelete="SET NULL",
        ),
        sa.ForeignKeyConstraint(
            ["team_id"],
            ["teams.id"],
            name=op.f("fk_team_invitations_team_id_teams"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["user_id"],
            ["users.id"],
            name=op.f("fk_team_invitations_user_id_users"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_team_invitations")),
        sa.UniqueConstraint("team_id", "user_id", name=op.f("uq_team_invitations_team_id")),
    )
    op.create_index(
        op.f("ix_team_invitations_user_id"), "team_invitations", ["user_id"], unique=False
    )
    with op.batch_alter_table("challenges", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column("team_mode", sa.Boolean(), nullable=False, server_default=sa.false())
        )
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("team_id", sa.Integer(), nullable=True))
        batch_op.create_index(batch_op.f("ix_submissions_team_id"), ["team_id"], unique=False)
        batch_op.create_foreign_key(
            batch_op.f("fk_submissions_team_id_teams"),
            "teams",
            ["team_id"],
            ["id"],
            ondelete="SET NULL",
        )
    with op.batch_alter_table("leaderboard_entries", schema=None) as batch_op:
        batch_op.add_column(sa.Column("team_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("team_name", sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column("team_display_name", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("method", sa.String(length=100), nullable=True))
        batch_op.add_column(sa.Column("paper_url", sa.String(length=500), nullable=True))
        batch_op.add_column(sa.Column("code_url", sa.String(length=500), nullable=True))
        batch_op.create_index(
            batch_op.f("ix_leaderboard_entries_team_id"), ["team_id"], unique=False
        )
        batch_op.create_unique_constraint(
            "uq_leaderboard_entries_phase_team", ["phase_id", "team_id"]
        )
        batch_op.create_foreign_key(
            batch_op.f("fk_leaderboard_entries_team_id_teams"),
            "teams",
            ["team_id"],
            ["id"],
            ondelete="CASCADE",
        )
    # Rows stored before they held the method show it at once, not at their next refresh.
    for column in ("method", "paper_url", "code_url"):
        op.execute(
            f"UPDATE leaderboard_entries SET {column} = (SELECT submissions.{column} "
            "FROM submissions WHERE submissions.id = leaderboard_entries.submission_id)"
        )


def downgrade() -> None:
    with op.batch_alter_table("leaderboard_entries", schema=None) as batch_op:
        batch_op.drop_constraint(
            batch_op.f("fk_leaderboard_entries_team_id_teams"), type_="foreignkey"
        )
        batch_op.drop_constraint("uq_leaderboard_entries_phase_team", type_="unique")
        batch_op.drop_index(batch_op.f("ix_leaderboard_entries_team_id"))
        for column in ("code_url", "paper_url", "method", "team_display_name", "team_name"):
            batch_op.drop_column(column)
        batch_op.drop_column("team_id")
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.drop_constraint(batch_op.f("fk_submissions_team_id_teams"), type_="foreignkey")
        batch_op.drop_index(batch_op.f("ix_submissions_team_id"))
        batch_op.drop_column("team_id")
    with op.batch_alter_table("challenges", schema=None) as batch_op:
        batch_op.drop_column("team_mode")
    op.drop_index(op.f("ix_team_invitations_user_id"), table_name="team_invitations")
    op.drop_table("team_invitations")
    op.drop_index(op.f("ix_team_members_team_id"), table_name="team_members")
    op.drop_table("team_members")
    op.drop_table("teams")
