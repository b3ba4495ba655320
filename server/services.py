"""The app's services: one object per process, built by `create_app` (server/app.py) and read
by each request as `request.app.state.services`. Each part declares what it reads of it as a
protocol (`server/kit/deps.py`, `server/submissions/deps.py`, `server/leaderboard/deps.py`);
this class says it is all of them, and mypy holds it to that."""

from __future__ import annotations

from dataclasses import dataclass, field

from sqlalchemy.orm import Session as DB
from sqlalchemy.orm import sessionmaker

from server.kit.ratelimit import RateLimiter
from server.kit.settings import Settings
from server.leaderboard.deps import BoardServices
from server.leaderboard.rendered import BoardPages
from server.leaderboard.snapshot import Snapshots
from server.submissions.deps import SubmissionServices
from server.submissions.outbox import Dispatcher
from server.submissions.service import Resolver


@dataclass
class Services(SubmissionServices, BoardServices):
    settings: Settings
    sessions: sessionmaker[DB]
    limiter: RateLimiter
    resolve: Resolver
    dispatcher: Dispatcher
    board_pages: BoardPages = field(default_factory=BoardPages)
    boards: Snapshots = field(init=False)

    def __post_init__(self) -> None:
        self.boards = Snapshots(self.settings.leaderboard_max_age)

    @property
    def csrf_key(self) -> bytes:
        return self.settings.secret("secret_key").encode()
