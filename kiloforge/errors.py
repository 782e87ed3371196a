"""User-facing errors: every one is a single line, so a CLI prints ``error: <message>`` without a traceback.

:class:`KiloforgeError` is the base of every error raised for bad input (a corrupt policy file, a
policy the int8 format cannot hold, an output path that cannot be written); the exporter's own
errors (:mod:`export.errors`) derive from it too. A message may quote text read from a file (a
name, a field, a path); :func:`printable` escapes what a terminal would interpret, and every
error message goes through it.
"""
from __future__ import annotations


def printable(text: object, limit: int | None = None) -> str:
    """``text`` with every non-printable character (control, format, separator, unassigned) escaped
    as ``\\xNN`` / ``\\uNNNN``, so that text from a file cannot move the cursor, recolour or
    rewrite a terminal; cut to ``limit`` characters (with an ellipsis) when given.

    >>> printable("ok \\x1b[2Jname\\u202e")
    'ok \\\\x1b[2Jname\\\\u202e'
    """
    s = str(text)
    if not s.isprintable():
        s = "".join(c if c.isprintable() else
                    f"\\x{ord(c):02x}" if ord(c) < 0x100 else
                    f"\\u{ord(c):04x}" if ord(c) < 0x10000 else f"\\U{ord(c):08x}" for c in s)
    if limit is not None and len(s) > limit:
        s = s[:max(0, limit - 3)] + "..."
    return s


def one_line(msg: object) -> str:
    """Collapse a message onto one line (newlines become '; '), every other control character escaped.

    >>> one_line("a\\n  b\\n")
    'a; b'
    >>> one_line("bell\\a")
    'bell\\\\x07'
    """
    parts = [printable(p.strip()) for p in str(msg).splitlines()]
    return "; ".join(p for p in parts if p)


def os_error_text(e: OSError, name: bool = True) -> str:
    """An operating-system error in words, for one line: ``'<file>': <reason>`` (``name``: with the file).

    >>> os_error_text(OSError(36, "File name too long", "x" * 300))[-30:]
    "xxxxxx...': File name too long"
    """
    reason = printable(e.strerror or type(e).__name__)
    if name and e.filename is not None:
        return f"'{printable(e.filename, 120)}': {reason}"
    return reason


class KiloforgeError(Exception):
    """Base of every user-facing error; ``str(err)`` is one line."""

    def __init__(self, msg: object) -> None:
        super().__init__(one_line(msg))


class InputError(KiloforgeError, ValueError):
    """An external input (a file, a JSON field, a command-line number) is malformed or out of range."""


class PolicyError(InputError):
    """A policy artifact is missing, unreadable, corrupt or inconsistent with its world."""


class QuantizeError(KiloforgeError):
    """A policy cannot be represented in the int8 number format (e.g. a provable int32 overflow)."""


class OutputError(KiloforgeError):
    """An output file cannot be written."""
