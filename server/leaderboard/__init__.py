"""Leaderboards: one stored row per participant and baseline, kept whole per phase in memory."""
