"""``python -m learn train`` (MAGDDPG), ``train-recurrent`` (MAGRDPG) and ``train-es`` (evolution strategies):
every config field is a flag (tyro).

    python -m learn train --robots 4 --history 20 --preset fast --world kilobot --out runs/NAME
    python -m learn train-recurrent --preset guided --robots 2 --out runs/NAME
    python -m learn train-es --robots 4 16 32 --seed 1 --out runs/NAME
    python -m learn train --out runs/NAME --resume [--episodes N] [--max-minutes M]

Besides the config fields (``--help`` lists them with their docs; ``--robots`` = ``--n-robots``,
``--history`` = ``--t-prev``): ``--preset`` (training preset), ``--config`` (JSON file of fields),
``--out`` (run directory), ``--resume`` (continue ``--out`` from its checkpoint; a run directory
without one restarts), ``--quiet`` (no progress bar). Precedence: defaults < ``--preset`` <
``--config`` < flags; with ``--resume`` the run's config.json, then flags (only budgets and speed
knobs may change). User errors print one line and exit 2; an interrupted run exits 130 / 143.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import os
import re
import shlex
import sys
import typing
from pathlib import Path
from typing import Annotated, Any, Callable, Literal, Optional

import tyro

from kiloforge.cliparse import first_unknown_option, unknown_option, version_line

from sim.config import PRESETS as WORLD_PRESETS
from sim.tasks import DEFAULT_TASK

from .config import FLAG_ALIASES, PRESETS, ConfigBase, ConfigError, ESConfig, RecurrentConfig, TrainConfig, flag_name
from .runfiles import read_json

_BOX = re.compile(r"[╭╮╰╯│]")


#: the run options of both commands: (name, type, default, help)
RUN_OPTIONS = (("preset", Optional[str], None, "training preset (the world is --world)"),
               ("config", Optional[str], None, "JSON file of config fields"),
               ("out", Optional[str], None, "run directory (default runs/<task>__<exp>__<seed>__<time>)"),
               ("resume", bool, False, "continue the run in --out from its checkpoint (one without a checkpoint restarts)"),
               ("quiet", bool, False, "no progress bar; one line per evaluation"),
               ("version", tyro.conf.FlagCreatePairsOff[bool], False, "print the version and exit"))
RUN_METAVARS = {"config": "FILE", "out": "DIR"}  #: what --help shows for a run option's value


def _args_class(cls: type[ConfigBase], default_preset: str) -> type:
    """The CLI of one config class: its fields (no prefix), then the run options (``--preset``: one of the
    algorithm's training presets, listed by ``--help``)."""
    preset = (Literal[tuple(PRESETS[cls.algorithm])], default_preset)  # type: ignore[valid-type]
    fields = [("cfg", Annotated[cls, tyro.conf.arg(name="")])]
    for name, typ, default, doc in RUN_OPTIONS:
        typ, default = preset if name == "preset" else (typ, default)
        fields.append((name, Annotated[typ, tyro.conf.arg(help=doc, metavar=RUN_METAVARS.get(name))],
                       dataclasses.field(default=default)))
    Args = dataclasses.make_dataclass("Args", fields)
    Args.__doc__ = cls.__doc__
    return Args


def base_config(cls: type[ConfigBase], preset: str | None, config: str | None, resume: bool,
                out: str | None, default_preset: str) -> ConfigBase:
    """defaults < preset < config file; with ``resume`` the run's own config.json."""
    if resume:
        if not out:
            raise ConfigError("--resume needs --out RUN_DIR")
        path = Path(out) / "config.json"
        if not path.is_file():
            raise ConfigError(f"cannot resume: '{path}' does not exist")
        return cls.from_dict(read_json(path))
    presets = PRESETS[cls.algorithm]
    name = preset or default_preset
    if name not in presets:
        hint = f"'{name}' is a world: use --world {name}; " if name in WORLD_PRESETS else ""
        raise ConfigError(f"--preset: {hint}training presets are {', '.join(presets)}")
    cfg = cls.from_dict(presets[name])
    if config:
        cfg = cls.from_dict(read_json(Path(config)), base=cfg)
    return cfg


def _tyro_error(text: str) -> str:
    """The first message of tyro's boxed error output, as one line."""
    lines = []
    for raw in text.splitlines():
        line = _BOX.sub("", raw).strip()
        if line.startswith("─"):  # the box's title or a separator
            if lines:
                break
            continue
        if line:
            lines.append(line)
    msg = " ".join(lines) or "bad arguments (see --help)"
    m = re.match(r"Error parsing (--[\w-]+): (.*)", msg)
    if m:  # name the config field, as the JSON errors do
        msg = f"{m.group(1)[2:].replace('-', '_')} ({m.group(1)}): {m.group(2)}"
    return msg


def train_flags(cls: type[ConfigBase]) -> set[str]:
    """Every option of a trainer's command line: its config fields' flags (with their aliases and the
    ``--no-`` form of booleans), the run options, ``--help``."""
    hints = {**typing.get_type_hints(cls), **{name: typ for name, typ, _, _ in RUN_OPTIONS}}
    names = [f.name for f in dataclasses.fields(cls)] + [name for name, *_ in RUN_OPTIONS]
    flags = {"-h", "--help"} | {FLAG_ALIASES[n] for n in names if n in FLAG_ALIASES}
    for name in names:
        flags.add("--" + name.replace("_", "-"))
        if hints[name] is bool:
            flags.add("--no-" + name.replace("_", "-"))
    return flags


def parse_train_args(argv: list[str], cls: type[ConfigBase], prog: str, default_preset: str):
    """(config, run directory, resume, quiet) from the command line; ConfigError (one line) on bad input."""
    unknown = first_unknown_option(argv, train_flags(cls))
    if unknown is not None:
        raise ConfigError(unknown_option(unknown, train_flags(cls) - {"-h"}))
    meta = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    for flag in ("--preset", "--config", "--out"):
        meta.add_argument(flag, default=None)
    meta.add_argument("--resume", action="store_true")
    meta.add_argument("--version", action="version", version=version_line())
    known, _ = meta.parse_known_args(argv)
    base = base_config(cls, known.preset, known.config, known.resume, known.out, default_preset)
    Args = _args_class(cls, default_preset)
    default = Args(cfg=base, preset=known.preset or default_preset, config=known.config, out=known.out, resume=known.resume)
    err = io.StringIO()
    columns = os.environ.get("COLUMNS")
    if not {"-h", "--help"} & set(argv):
        os.environ["COLUMNS"] = "400"  # tyro's rich error boxes: one message per line
    try:
        with contextlib.redirect_stderr(err):
            args = tyro.cli(Args, args=argv, default=default, prog=prog, config=(tyro.conf.OmitArgPrefixes,))
    except SystemExit as e:
        if e.code:
            raise ConfigError(_tyro_error(err.getvalue())) from None
        raise
    except BrokenPipeError:  # --help piped into a reader that stopped early (| head): done, as argparse's help is
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit's flush must not fail again
        raise SystemExit(0) from None
    finally:
        if columns is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = columns
    cfg = args.cfg.validate()
    if args.out:
        out = Path(args.out)
    else:
        from .rundir import run_name

        out = Path("runs") / run_name(cfg)
    return cfg, out, args.resume, args.quiet


def report_rl(res, cfg: ConfigBase) -> None:
    """What a MAGDDPG / MAGRDPG run prints when it ends."""
    from .evaluate import row_summary

    c = res.counters
    best = max(c.rows, key=lambda r: r["eval_return"]) if c.rows else None
    print(f"  {c.env_steps} transitions, {c.updates} updates in {c.wall_s:.0f} s: "
          f"{c.env_steps / c.env_s if c.env_s else float('nan'):.0f} env steps/s while collecting, "
          f"{c.updates / c.update_s if c.update_s else float('nan'):.0f} updates/s while updating")
    if best:
        print(f"  best evaluation at {best['env_steps']:.0f} transitions: return {best['eval_return']:.1f}, "
              f"{row_summary(best, cfg.task_spec())}")


def report_es(res, cfg: ConfigBase) -> None:
    """What an ES run prints when it ends."""
    from .evaluate import success_panel

    c = res.counters
    col, label = success_panel(cfg.task_spec())
    print(f"  {c.rows[-1]['generation'] if c.rows else 0:.0f} generations, {c.env_steps} env steps in {c.wall_s:.0f} s")
    if c.rows:
        best = max(c.rows, key=lambda r: r[col])
        sizes = "  ".join(f"{k[len(col + '_m'):]} robots {v:.3f}" for k, v in best.items() if k.startswith(col + "_m"))
        print(f"  best evaluation at generation {best['generation']:.0f}: {label} "
              f"{best[col]:.3f}{'  (' + sizes + ')' if sizes else ''}")


def _rl_trainer():
    from .train import train

    return train


def _es_trainer():
    from .es_train import train_es

    return train_es


#: per algorithm: (the trainer, loaded lazily; what its run prints at the end)
TRAINERS = {"magddpg": (_rl_trainer, report_rl), "magrdpg": (_rl_trainer, report_rl), "es": (_es_trainer, report_es)}


def main_train(argv: list[str] | None = None, cls: type[ConfigBase] = TrainConfig,
               prog: str = "python -m learn train", default_preset: str = "default") -> int:
    """CLI entry point of one algorithm; returns the exit status."""
    from kiloforge.cliparse import program
    from kiloforge.errors import KiloforgeError
    from kiloforge.interrupts import exit_status

    prog = program(prog)
    argv = sys.argv[1:] if argv is None else list(argv)
    load, report = TRAINERS[cls.algorithm]
    res = None
    try:
        train = load()
        cfg, out, resume, quiet = parse_train_args(argv, cls, prog, default_preset)
        note = cfg.budget_note()
        if note:
            print(f"note: {note}; it trains, but the exporter will refuse it", file=sys.stderr)
        res = train(cfg, out, resume=resume, progress=not quiet)
        _report(res, report, prog, cfg)
    except (ConfigError, KiloforgeError, ValueError) as e:
        print(f"{prog}: error: {as_flags(str(e), cls)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # outside the trainer's own handling (which checkpoints): loading, setting up, ending
        if res is not None:
            print(f"{prog}: error: interrupted while reporting; the run in {res.run_dir} is complete", file=sys.stderr)
        else:
            print(f"{prog}: error: interrupted; the run directory keeps its last checkpoint, if any "
                  "(--resume continues it, or restarts a run without one)", file=sys.stderr)
        return exit_status(e)
    return res.exit_status


def as_flags(msg: str, cls: type[ConfigBase]) -> str:
    """A validation message that starts with a config field's name (``n_robots must be …``), starting with the
    flag a user typed instead (``--robots must be …``)."""
    head, sep, rest = msg.partition(" ")
    if head not in {f.name for f in dataclasses.fields(cls)}:
        return msg
    flag = flag_name(head)
    if rest.startswith("(--") and ")" in rest:  # tyro's own messages name the flag already: "field (--flag): …"
        return flag + rest.partition(")")[2]
    return flag + sep + rest


def _report(res: Any, report: Callable[[Any, ConfigBase], None], prog: str, cfg: ConfigBase) -> None:
    """What a finished run prints: where it is, its numbers, its policies and, last, the export command of its
    result (:func:`learn.rundir.result_policy`)."""
    from .rundir import result_policy

    print(f"run: {res.run_dir}  ({res.stopped})")
    report(res, cfg)
    pols = [res.run_dir / n for n in ("policy_best.npz", "policy_last.npz", "policy_bc.npz")
            if (res.run_dir / n).is_file()]
    print(f"  policies: {', '.join(map(str, pols)) if pols else 'none (no evaluation ran)'}")
    if pols:
        result = res.run_dir / result_policy(cfg)
        result = result if result.is_file() else pols[0]
        exporter = "kiloforge export" if prog.startswith("kiloforge") else "python -m export"
        print(f"  result: {result}")
        task = "" if cfg.task == DEFAULT_TASK else f" --task {shlex.quote(cfg.task)}"
        print(f"  next: {exporter}{task} --policy {shlex.quote(str(result))} --out kilobot_policy.c   (the firmware C of "
              f"the run's result)")


def main_train_recurrent(argv: list[str] | None = None, prog: str = "python -m learn train-recurrent") -> int:
    """``python -m learn train-recurrent``: MAGRDPG (default preset ``fast``)."""
    return main_train(argv, RecurrentConfig, prog, "fast")


def main_train_es(argv: list[str] | None = None, prog: str = "python -m learn train-es") -> int:
    """``python -m learn train-es``: evolution strategies from a behaviour-cloned MLP (learn.es_train)."""
    return main_train(argv, ESConfig, prog, "default")

