"""Exporter errors: user mistakes become one-line messages (the CLI prints them and exits non-zero).

Every error raised for bad input (a corrupt policy file, an over-budget architecture, an output path
that cannot be written) is an :class:`ExportError`. Its text is always a single line, so the CLI can
print ``error: <message>`` without a traceback.
"""
from __future__ import annotations


def one_line(msg: object) -> str:
    """Collapse a message onto one line (newlines become '; ').

    >>> one_line("a\\n  b\\n")
    'a; b'
    """
    parts = [p.strip() for p in str(msg).splitlines()]
    return "; ".join(p for p in parts if p)


class ExportError(Exception):
    """Base of every user-facing exporter error; ``str(err)`` is one line."""

    def __init__(self, msg: object) -> None:
        super().__init__(one_line(msg))


class PolicyError(ExportError):
    """A policy artifact is missing, unreadable, corrupt or inconsistent with its world."""


class QuantizeError(ExportError):
    """A policy cannot be represented in the int8 number format (e.g. a provable int32 overflow)."""


class BudgetError(ExportError):
    """An architecture does not fit the Kilobot's flash or SRAM budget."""


class OutputError(ExportError):
    """An output file cannot be written."""


class VerifyError(ExportError):
    """The rendered firmware does not behave like the emulator (a bug, never a user mistake)."""
