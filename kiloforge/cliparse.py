"""What every command line of the project shares: a strict argument parser and the name it goes by.

* :class:`ArgumentParser` refuses abbreviated options (``--rob 4`` is an error, not ``--robots 4``)
  and reports a bad command line in one line with exit status 2;
* :func:`program` is the name a command calls itself in its messages: ``kiloforge train`` when it
  runs under the ``kiloforge`` command (:mod:`kiloforge.cli` sets it with :func:`invoked_as`), else
  the module's own (``python -m learn train``).
"""
from __future__ import annotations

import argparse
import typing
from contextlib import contextmanager
from typing import Iterator

from .errors import one_line

EXIT_USAGE = 2  #: bad input: a wrong command line, a missing file, a missing optional dependency

_invoked: list[tuple[str, str]] = []  #: (the module's name for itself, the name it goes by now)


def program(default: str) -> str:
    """``default`` (e.g. ``"python -m learn train"``), with the ``python -m`` form that the running
    ``kiloforge`` sub-command stands for replaced by that sub-command (``"kiloforge learn train"``)."""
    if _invoked:
        module_form, name = _invoked[-1]
        if default == module_form or default.startswith(module_form + " "):
            return name + default[len(module_form):]
    return default


@contextmanager
def invoked_as(module_form: str, name: str) -> Iterator[None]:
    """Within the block :func:`program` writes ``module_form`` (``"python -m export verify"``) as
    ``name`` (``"kiloforge verify"``)."""
    _invoked.append((module_form, name))
    try:
        yield
    finally:
        _invoked.pop()


class ArgumentParser(argparse.ArgumentParser):
    """argparse without abbreviations, named by :func:`program`, with one-line errors (exit status 2)."""

    def __init__(self, *args: typing.Any, prog: str | None = None, **kwargs: typing.Any) -> None:
        kwargs["allow_abbrev"] = False
        super().__init__(*args, prog=None if prog is None else program(prog), **kwargs)

    def error(self, message: str) -> typing.NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {one_line(message)}\n")
