"""Generators of the data kiloforge ships (``python -m tools.NAME`` from the repository root): tools/README.md."""
