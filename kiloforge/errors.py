"""User-facing errors: every one is a single line, so a CLI prints ``error: <message>`` without a traceback.

:class:`KiloforgeError` is the base of every error raised for bad input (a corrupt policy file, a
policy the int8 format cannot hold, an output path that cannot be written); the exporter's own
errors (:mod:`export.errors`) derive from it too.
"""
from __future__ import annotations


def one_line(msg: object) -> str:
    """Collapse a message onto one line (newlines become '; ').

    >>> one_line("a\\n  b\\n")
    'a; b'
    """
    parts = [p.strip() for p in str(msg).splitlines()]
    return "; ".join(p for p in parts if p)


class KiloforgeError(Exception):
    """Base of every user-facing error; ``str(err)`` is one line."""

    def __init__(self, msg: object) -> None:
        super().__init__(one_line(msg))


class PolicyError(KiloforgeError):
    """A policy artifact is missing, unreadable, corrupt or inconsistent with its world."""


class QuantizeError(KiloforgeError):
    """A policy cannot be represented in the int8 number format (e.g. a provable int32 overflow)."""


class OutputError(KiloforgeError):
    """An output file cannot be written."""
