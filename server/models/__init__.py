"""The database schema (SQLAlchemy 2.0 typed models), one module per domain.

Every public name is re-exported here, so ``from server.models import Submission`` works
whichever module defines it. Every relationship is ``lazy="raise"``: a query names what it
loads (``selectinload``, ``joinedload``), so no attribute access runs a query behind its back.
Alembic migrations in ``alembic/versions`` are the only way this schema reaches a database;
``alembic check`` in the tests proves the two agree.
"""

from internal_api.schemas import ACTIVE_STATES, FINAL_STATES, State
from server.models.accounts import ApiToken, Session, User
from server.models.audit import AuditRecord
from server.models.base import NAMING, Base, UTCDateTime, utcnow
from server.models.challenges import Challenge, Phase
from server.models.leaderboard import LeaderboardEntry
from server.models.submissions import (
    Cause,
    EpisodeResultRow,
    Outbox,
    Submission,
    TaskResultRow,
    Transition,
)
from server.models.teams import Team, TeamInvitation, TeamMember, team_id_of, team_of

__all__ = [
    "ACTIVE_STATES",
    "FINAL_STATES",
    "NAMING",
    "ApiToken",
    "AuditRecord",
    "Base",
    "Cause",
    "Challenge",
    "EpisodeResultRow",
    "LeaderboardEntry",
    "Outbox",
    "Phase",
    "Session",
    "State",
    "Submission",
    "TaskResultRow",
    "Team",
    "TeamInvitation",
    "TeamMember",
    "Transition",
    "UTCDateTime",
    "User",
    "team_id_of",
    "team_of",
    "utcnow",
]
