"""The ManiEval API server (FastAPI): accounts, challenges, submissions, leaderboards."""
