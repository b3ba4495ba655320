"""What ManiEval's tests and benchmarks share: a double of the Kubernetes API server (none can
run on a development machine), helpers that make users, challenges and submissions through the
real code paths, and workers wired to an in-process server. Never imported by the product
(import-linter checks it)."""
