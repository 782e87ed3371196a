"""``python -m export budget``: will an actor of this size fit on a Kilobot, before training?

    python -m export budget --history 20 --hidden 32 32 [--world kilobot]     (an MLP actor)
    python -m export budget --gru 32 [--world kilobot]                        (a GRU actor)

Every actor kind brings its own size flags (:attr:`kiloforge.actors.base.ActorKind.budget_options`);
the flags given select the kind. Exit 0 fits, 1 does not (and what would fit), 2 bad input.
"""
from __future__ import annotations

import argparse
from typing import Sequence

from kiloforge.actors.registry import KINDS
from kiloforge.cliparse import deprecated_alias
from sim.config import DEFAULT_WORLD, PRESETS, preset
from sim.tasks import get_task

from ..codegen import budget as bud
from ..errors import ExportError
from .common import EXIT_FAIL, EXIT_OK, Parser, add_task, positive


def budget_parser() -> argparse.ArgumentParser:
    kinds = ", ".join(f"{k.budget_usage} ({k.name})" for k in KINDS.values())
    ap = Parser(prog="python -m export budget",
                description=f"Will an actor of this size fit on a Kilobot? Give the sizes of one actor kind: {kinds}. "
                            "Exit 0 fits, 1 does not.")
    for kind in KINDS.values():
        for o in kind.budget_options:
            ap.add_argument(o.flag, dest=o.dest, type=positive if o.positive else str, nargs=o.nargs,
                            default=o.default, metavar=o.metavar, choices=o.choices, help=o.help)
    deprecated_alias(ap, "--preset", ap.add_argument("--world", default=DEFAULT_WORLD, choices=sorted(PRESETS),
                                                     help=f"world preset (default {DEFAULT_WORLD})"))
    add_task(ap)
    return ap


def run_budget(argv: Sequence[str]) -> int:
    args = budget_parser().parse_args(list(argv))
    values = vars(args)
    try:
        task = get_task(args.task)
        world = task.world(preset(args.world))
        task.check_world(world)
    except ValueError as e:
        raise ExportError(str(e)) from None
    chosen = [k for k in KINDS.values()
              if any(o.claims and values[o.dest] not in (None, [], ()) for o in k.budget_options)]
    if len(chosen) != 1:
        usages = " or ".join(f"{k.budget_usage} ({k.name} actor)" for k in (chosen or KINDS.values()))
        raise ExportError(f"give the sizes of one actor: {usages}")
    kind = chosen[0]
    try:
        arch = kind.budget_arch(values)
    except ValueError as e:
        raise ExportError(str(e)) from None
    b = bud.estimate(kind, world, arch)
    print(b.table())
    if b.ok:
        return EXIT_OK
    print("would fit: " + "; ".join(b.suggest()))
    return EXIT_FAIL
