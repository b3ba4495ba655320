"""Teams: create, invite, accept, leave; per-team quotas and leaderboard rows in team mode."""
