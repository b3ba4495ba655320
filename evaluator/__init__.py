"""Runs a policy against ManiSkill tasks and scores it; imports nothing from server/ or worker/."""
