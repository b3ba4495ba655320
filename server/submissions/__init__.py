"""Submissions: accept and pin an image, quota, the state machine, the outbox to the queue,
the reports of the workers, and the pages that follow an evaluation live."""
