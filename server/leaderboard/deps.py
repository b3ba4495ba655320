"""What the leaderboard's routes use of the app's services (built in server/services.py): the
plumbing every route has, each phase's board and the rendered pages."""

from __future__ import annotations

from typing import Protocol

from fastapi import Request

from server.kit.deps import Plumbing
from server.leaderboard.rendered import BoardPages
from server.leaderboard.snapshot import Snapshots


class BoardServices(Plumbing, Protocol):
    boards: Snapshots
    """Whole boards per phase for the leaderboard API and pages (server/leaderboard/snapshot.py)."""
    board_pages: BoardPages
    """Rendered leaderboard page contents (server/leaderboard/pages.py)."""


def services(request: Request) -> BoardServices:
    found: BoardServices = request.app.state.services
    return found
