"""user names are unique regardless of case: a unique index on lower(username)

Existing names that differ only in case are not merged or renamed here (that would lose or
change someone's account): the upgrade stops and names them, for an operator to settle.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def case_duplicates(names: Sequence[str]) -> list[list[str]]:
    """The groups of `names` that differ only in case, each sorted, in order."""
    groups: dict[str, list[str]] = {}
    for name in names:
        groups.setdefault(name.lower(), []).append(name)
    return sorted(sorted(group) for group in groups.values() if len(group) > 1)


def upgrade() -> None:
    names = op.get_bind().execute(sa.text("SELECT username FROM users")).scalars().all()
    if clashes := case_duplicates(names):
        listed = "; ".join(", ".join(group) for group in clashes)
        raise RuntimeError(
            "cannot make user names unique regardless of case: these accounts' names differ "
            f"only in case: {listed}. Rename all but one of each group (UPDATE users SET "
            "username = ... WHERE id = ...), then upgrade again."
        )
    op.create_index("uq_users_username_lower", "users", [sa.text("lower(username)")], unique=True)


def downgrade() -> None:
    op.drop_index("uq_users_username_lower", table_name="users")
