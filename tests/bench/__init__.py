"""Benchmarks: scripts that measure and print tables (``python -m tests.bench.NAME`` from the repository root)."""
