"""The exporter's own errors (every one a single line; bad-input errors shared with the rest of
kiloforge are in :mod:`kiloforge.errors`)."""
from __future__ import annotations

from kiloforge.errors import KiloforgeError


class ExportError(KiloforgeError):
    """A bad argument of the exporter (a target uid, a message type, a C identifier, ...)."""


class BudgetError(ExportError):
    """An architecture does not fit the Kilobot's flash or SRAM budget."""


class VerifyError(ExportError):
    """The rendered firmware does not behave like the emulator (a bug, never a user mistake)."""
