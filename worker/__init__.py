"""Celery tasks and the executors that run evaluations (in-process, Docker API, Kubernetes)."""
