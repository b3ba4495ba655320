"""ManiEval: evaluation service for simulated robot-manipulation benchmarks."""

__version__ = "0.1.0"
