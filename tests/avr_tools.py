"""Shared guard of the AVR tests: skip locally when the toolchain is missing, fail in CI."""
from __future__ import annotations

import os

import pytest

from export.verify import avr


def require_avr(simulate: bool = False) -> None:
    """Skip (locally) or fail (when the environment variable CI is set) without avr-gcc / simavr.

    ``simulate`` also needs gcc and simavr's headers and library (``libsimavr-dev``).
    """
    why = avr.missing_tools(simulate=simulate)
    if why is None:
        return
    if os.environ.get("CI"):
        pytest.fail(f"CI must run the AVR tests: {why}")
    pytest.skip(why)
