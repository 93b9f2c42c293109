"""Benchmarks of liuxing_envs; each module runs with ``python -m benchmarks.<name>``."""
