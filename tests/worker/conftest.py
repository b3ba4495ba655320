"""Worker tests share the server's database fixtures (SQLite and Postgres, rolled back)."""

from tests.server.conftest import (  # noqa: F401 - pytest fixtures
    committed_sessions,
    db,
    engine,
    postgres_url,
    sessions,
    settings,
    sqlite_url,
)
