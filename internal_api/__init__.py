"""The contract between the server and its workers: the bodies of ``/internal/v1``, the
submission states both sides speak of, and the names of the broker's tasks and queues.

Neutral ground: the server and the worker both import it, and it imports neither of them
(only the evaluator's plan and result documents, which both sides exchange).
"""
