"""What every command line of the project shares: a strict argument parser and the name it goes by.

* :class:`ArgumentParser` refuses abbreviated options (``--rob 4`` is an error, not ``--robots 4``)
  and reports a bad command line in one line with exit status 2;
* every parser has ``--version`` (:func:`version_line`, the same line for every command);
* an unknown option is answered with the closest valid one (:func:`unknown_option`:
  ``unrecognized option --robot; did you mean --robots?``), also by the tyro parsers of :mod:`learn.cli`;
* :func:`deprecated_alias` keeps an old spelling of a renamed flag working, with a one-line note;
  :func:`deprecated_noop` accepts a flag that does nothing any more, with a one-line note saying so;
* :func:`program` is the name a command calls itself in its messages: ``kiloforge train`` when it
  runs under the ``kiloforge`` command (:mod:`kiloforge.cli` sets it with :func:`invoked_as`), else
  the module's own (``python -m learn train``). Every error line reads ``<program>: error: <message>``.

The flags that mean the same thing have one name in every command: ``--world`` (a world preset),
``--preset`` (a training preset, only in ``learn``), ``--robots`` (swarm sizes, up to
:data:`sim.config.MAX_ROBOTS`), ``--n-envs`` (environments simulated together), ``--quiet`` (no
progress output), ``--seed``, ``--episodes``, ``--steps``, ``--out``, ``--policy``.
"""
from __future__ import annotations

import argparse
import difflib
import itertools
import sys
import typing
from contextlib import contextmanager
from typing import Iterable, Iterator, Sequence

from . import __version__
from .errors import one_line, printable

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


def version_line() -> str:
    """What ``--version`` prints, the same for every command: ``kiloforge 0.2.0``."""
    return f"kiloforge {__version__}"


def error_line(prog: str, message: object) -> str:
    """The one error line every command prints: ``<prog>: error: <message>``."""
    return f"{prog}: error: {one_line(message)}"


def unknown_option(token: str, valid: Iterable[str]) -> str:
    """The message for an option no parser knows: ``unrecognized option --robot; did you mean --robots?``
    (the closest of ``valid``; without a close one, where the options are listed)."""
    name = token.partition("=")[0]
    close = difflib.get_close_matches(name, sorted(set(valid)), n=1)
    hint = f"; did you mean {close[0]}?" if close else " (--help lists the options)"
    return f"unrecognized option {printable(name, 60)}{hint}"


def first_unknown_option(argv: Sequence[str], known: Iterable[str]) -> str | None:
    """The first ``--option`` of ``argv`` (``--name=value`` too) that is not in ``known``, before ``--``;
    None when every one is known."""
    known = set(known)
    for token in argv:
        if token == "--":
            return None
        if token.startswith("--") and token.partition("=")[0] not in known:
            return token
    return None


class _DeprecatedAlias(argparse.Action):
    """An old spelling of a flag: stores into the new flag's ``dest`` after a one-line note on stderr."""

    def __init__(self, option_strings: list[str], dest: str, new: str = "", **kwargs: typing.Any) -> None:
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: typing.Any,
                 option_string: str | None = None) -> None:
        print(f"{parser.prog}: note: {option_string} is deprecated, use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)


def deprecated_alias(parser: argparse.ArgumentParser, old: str, action: argparse.Action) -> None:
    """Accept ``old`` (hidden from ``--help``) for the flag ``action`` (what ``add_argument`` returned),
    with a one-line deprecation note when it is used."""
    parser.add_argument(old, action=_DeprecatedAlias, new=action.option_strings[0], dest=action.dest,
                        nargs=action.nargs, const=action.const, type=action.type, choices=action.choices,
                        metavar=action.metavar, help=argparse.SUPPRESS)


class _NoOpFlag(argparse.Action):
    """A flag that no longer does anything: accepted with a one-line note on stderr."""

    def __init__(self, option_strings: list[str], dest: str, why: str = "", **kwargs: typing.Any) -> None:
        self.why = why
        super().__init__(option_strings, argparse.SUPPRESS, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: typing.Any,
                 option_string: str | None = None) -> None:
        print(f"{parser.prog}: note: {option_string} does nothing ({self.why}) and will be removed; leave it out",
              file=sys.stderr)


def deprecated_noop(parser: argparse.ArgumentParser, flag: str, why: str) -> None:
    """Accept the flag ``flag`` that does nothing any more (hidden from ``--help``), with a one-line note saying
    so (``why``: the reason) when it is used."""
    parser.add_argument(flag, action=_NoOpFlag, why=why, help=argparse.SUPPRESS)


class ArgumentParser(argparse.ArgumentParser):
    """argparse without abbreviations, named by :func:`program`, with ``--version`` and one-line errors
    (exit status 2)."""

    def __init__(self, *args: typing.Any, prog: str | None = None, **kwargs: typing.Any) -> None:
        kwargs["allow_abbrev"] = False
        super().__init__(*args, prog=None if prog is None else program(prog), **kwargs)
        if kwargs.get("add_help", True):
            self.add_argument("--version", action="version", version=version_line(),
                              help="print the version and exit")

    def parse_known_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None):  # type: ignore[override]
        self._argv = list(sys.argv[1:] if args is None else args)  # for error(): which option was misspelled
        return super().parse_known_args(args, namespace)

    def explain(self, message: str) -> str:
        """argparse's ``message``, or, when the command line has a misspelled option, that option with the
        closest valid one (a missing required option or a stray value is usually its consequence)."""
        argv = getattr(self, "_argv", [])
        if any(isinstance(a, argparse._SubParsersAction) for a in self._actions):  # a sub-command's options are its own
            argv = list(itertools.takewhile(lambda t: t.startswith("-"), argv))
        token = first_unknown_option(argv, self._option_string_actions)
        if token is None:
            return message
        return unknown_option(token, [s for a in self._actions if a.help != argparse.SUPPRESS for s in a.option_strings])

    def error(self, message: str) -> typing.NoReturn:
        self.exit(EXIT_USAGE, error_line(self.prog, self.explain(message)) + "\n")
