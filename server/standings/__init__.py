"""Standings: the stored leaderboard rows (`leaderboard_entries`), each participant's best
result per phase. The domains whose changes move a board keep them in step (a submission's
end, a team change, a challenge's team mode); the leaderboard reads them."""
