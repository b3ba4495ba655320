"""The broker's task names: the server sends wake-ups by name and never imports the worker."""

RUN_NEXT = "manieval.run_next"
"""A wake-up: a worker claims the fairest queued submission (the ids in it are only hints)."""
WATCH = "manieval.watch"
"""Take over watching a running attempt's Kubernetes Job (its first watcher was lost)."""
RECONCILE = "manieval.reconcile"
"""One reconciling pass; runs on its own queue so busy evaluation workers never delay it."""
