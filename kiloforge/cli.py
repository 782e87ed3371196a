"""``kiloforge``: the project's one command; each sub-command runs an existing entry point.

    kiloforge sim --policy baseline --robots 4 --out runs/demo
    kiloforge train --preset quick --world kilobot --out runs/q
    kiloforge evaluate --policy runs/q/policy_best.npz --robots 16 --out runs/q/eval
    kiloforge export --policy runs/q/policy_best.npz --out kilobot_policy.c
    kiloforge --version

:data:`COMMANDS` maps a sub-command to the module whose ``main(argv)`` runs it and the arguments put
before the user's (``kiloforge verify ...`` is ``python -m export verify ...``); the flags are the
delegate's own. Unlike ``python -m ...``, the installed ``kiloforge`` script does not put the working
directory first on ``sys.path``, so a ``sim.py`` or ``learn.py`` there cannot replace the packages;
where one does (``python -m kiloforge``, ``PYTHONPATH``) :func:`shadowing` says so in one line. A
missing optional dependency is one line naming the extra to install (:func:`kiloforge.extras.missing_extra`), exit 2.
"""
from __future__ import annotations

import difflib
import importlib
import importlib.util
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from . import __version__
from .cliparse import EXIT_USAGE, invoked_as
from .errors import printable
from .extras import missing_dependency

PACKAGES = ("kiloforge", "sim", "learn", "export", "firmware_templates")  #: the distribution's top-level packages


@dataclass(frozen=True)
class Command:
    module: str  #: the module whose ``main(argv) -> int`` runs the command
    prefix: tuple[str, ...]  #: arguments put before the user's
    summary: str  #: one line of ``kiloforge --help``


COMMANDS = {
    "sim": Command("sim.__main__", (), "run a policy in the simulator: metrics, plots, GIF, robustness suite"),
    "learn": Command("learn.__main__", (), "python -m learn: train, evaluate, plot, sweep, export-onnx"),
    "train": Command("learn.__main__", ("train",), "train an MLP policy with MAGDDPG (needs kiloforge[learn])"),
    "train-recurrent": Command("learn.__main__", ("train-recurrent",),
                               "train a recurrent (GRU/LSTM) policy with MAGRDPG (needs kiloforge[learn])"),
    "train-es": Command("learn.__main__", ("train-es",),
                        "train an MLP policy with evolution strategies from a searcher clone (needs kiloforge[learn])"),
    "evaluate": Command("learn.__main__", ("evaluate",), "evaluate .npz policies against the baselines"),
    "plot": Command("learn.__main__", ("plot",), "learning curves of run directories"),
    "sweep": Command("learn.__main__", ("sweep",), "a grid of trainings x seeds on Ray Tune (needs kiloforge[sweep])"),
    "export-onnx": Command("learn.__main__", ("export-onnx",), "write a policy's float actor as ONNX (needs kiloforge[onnx])"),
    "export": Command("export.__main__", (), "quantise a policy to int8 and write the Kilobot firmware C (and .hex)"),
    "verify": Command("export.__main__", ("verify",), "closed loop: int8 firmware emulator vs float actor in the simulator"),
    "budget": Command("export.__main__", ("budget",), "will an actor of this size fit on a Kilobot?"),
    "rehash": Command("export.__main__", ("rehash",), "give a policy file one trusts the hash of its contents"),
}


def usage() -> str:
    """``kiloforge --help``: one line per sub-command."""
    width = max(map(len, COMMANDS))
    lines = ["usage: kiloforge COMMAND [OPTIONS]   (kiloforge COMMAND --help: the command's options)", "",
             "Swarm policies from simulation to real Kilobot robots.", "", "commands:"]
    lines += [f"  {name:<{width}}  {c.summary}" for name, c in COMMANDS.items()]
    lines += ["", "  --version  print the version", "  --help     this list", "",
              "Exit status: 0 done, 1 a check failed (does not fit, verification failed), 2 bad input, "
              "130/143 interrupted, 141 standard output closed."]
    return "\n".join(lines)


def shadowing() -> str | None:
    """A one-line explanation when a top-level package of kiloforge is not the installed one (a stray
    ``sim.py`` in the working directory under ``python -m``), else None."""
    home = Path(__file__).resolve().parent.parent
    for name in PACKAGES:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        origin = spec.origin if spec is not None else None
        if spec is not None and spec.submodule_search_locations and origin and Path(origin).resolve().parent.parent == home:
            continue
        where = f"'{printable(origin)}'" if origin else "another module"
        return (f"{where} replaces kiloforge's '{name}' package (the working directory comes first on sys.path "
                f"under python -m); rename it, or run the installed 'kiloforge' command")
    return None


def run_guarded(prog: str, load: Callable[[], Callable[[list[str] | None], int]], argv: Sequence[str] | None,
                program: bool = True, held: Sequence[int] = ()) -> int:
    """``load()(argv)`` (``load`` imports the command and returns its ``main``; ``argv`` None: the program's
    own, ``sys.argv``) with the two checks of the module doc: shadowed packages first, then a missing
    dependency, reported as ``<prog> needs <module>: pip install 'kiloforge[<extra>]'`` (:func:`kiloforge.extras.missing_dependency`).
    ``program``: this is the process's own command line (signals are ignored once the command has returned;
    ``held``: what its ``__main__`` module held back, :func:`kiloforge.interrupts.as_program`); a Ctrl-C before
    the command's entry point took over ends in one line (130)."""
    from .interrupts import as_program, exit_status
    from .stdio import guarded_output

    def run() -> int:
        try:
            with as_program(held) if program else nullcontext():
                return _run_guarded(prog, load, argv)
        except KeyboardInterrupt as e:  # run_entry_point handles every one from its start to the program's end
            print(f"{prog}: error: interrupted before it started; nothing written", file=sys.stderr)
            return exit_status(e)

    return guarded_output(prog, run)


def _run_guarded(prog: str, load: Callable[[], Callable[[list[str] | None], int]], argv: Sequence[str] | None) -> int:
    from .interrupts import Interrupted, deferred

    try:
        with deferred():  # the entry point's own handling of Ctrl-C starts in load()(argv)
            problem = shadowing()
    except Interrupted as e:
        print(f"{prog}: error: interrupted before it started; nothing written", file=sys.stderr)
        return 128 + e.signum
    if problem:
        print(f"{prog}: error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    try:
        return load()(None if argv is None else list(argv))
    except ModuleNotFoundError as e:
        line = missing_dependency(prog, e)
        if line is None:
            raise
        print(line, file=sys.stderr)
        return EXIT_USAGE


def main(argv: Sequence[str] | None = None, held: Sequence[int] = ()) -> int:
    """Entry point of the ``kiloforge`` command; returns the exit status (``held``: the signals
    ``python -m kiloforge`` held back while it loaded, a list its holders go on appending to)."""
    from .interrupts import exit_status
    from .stdio import guarded_output

    def run() -> int:
        try:
            return _main(argv, held)
        except KeyboardInterrupt as e:  # before a command started (its entry point reports its own)
            print("kiloforge: error: interrupted; nothing written", file=sys.stderr)
            return exit_status(e)

    return guarded_output("kiloforge", run)


def _main(argv: Sequence[str] | None, held: Sequence[int]) -> int:
    program = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else EXIT_USAGE
    if argv[0] == "--version":
        print(f"kiloforge {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    cmd = COMMANDS.get(name)
    if cmd is None:
        close = difflib.get_close_matches(name, COMMANDS, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        print(f"kiloforge: error: unknown command '{printable(name, 60)}'; {hint}commands: {', '.join(COMMANDS)} "
              "(kiloforge --help)", file=sys.stderr)
        return EXIT_USAGE
    prog = f"kiloforge {name}"
    with invoked_as(" ".join(["python -m", cmd.module.partition(".")[0], *cmd.prefix]), prog):
        return run_guarded(prog, lambda: importlib.import_module(cmd.module).main, [*cmd.prefix, *rest], program, held)


def _script(package: str) -> Callable[..., int]:
    """The console script ``kiloforge-<package>``: ``python -m <package>`` with the checks of :func:`run_guarded`,
    its messages naming ``kiloforge-<package>`` (``held``: :mod:`kiloforge.scripts`)."""
    def script(held: Sequence[int] = ()) -> int:
        name = f"kiloforge-{package}"
        with invoked_as(f"python -m {package}", name):
            return run_guarded(name, lambda: importlib.import_module(f"{package}.__main__").main, None, held=held)

    script.__doc__ = f"Entry point of the ``kiloforge-{package}`` command."
    return script


sim_script, learn_script, export_script = map(_script, ("sim", "learn", "export"))

if __name__ == "__main__":
    sys.exit(main())
