"""Worker tests share the server's database fixtures (SQLite and Postgres, rolled back)."""
