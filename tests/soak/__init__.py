"""Soak runs: the long versions of checks the test suite runs CI-sized (``python -m tests.soak.NAME``)."""
