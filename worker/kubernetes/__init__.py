"""The Kubernetes executor: one Job per attempt.

`manifest` builds the Job (pure, no I/O), `status` reads Job, pod and event objects into the
executor's view (pure, no I/O), `client` talks to the API server with capped backoff, and
`watch` follows an attempt's Job to a final state.
"""
