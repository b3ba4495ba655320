"""The Kubernetes executor: one Job per attempt.

`manifest` builds the Job (pure, no I/O), `status` reads Job, pod and event objects into the
executor's view (pure, no I/O), `client` talks to the API server with capped backoff,
`informer` keeps one watched view of the evaluation Jobs and pods per process, and `watch`
follows an attempt's Job through it to a final state.
"""
