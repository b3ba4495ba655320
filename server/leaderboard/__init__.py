"""Leaderboards: one stored row per participant and baseline, read by the rank index."""
