"""Challenges: loaded from suite files, with their phases, seed commitments and pages."""
