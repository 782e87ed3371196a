"""``python -m learn sweep``: a grid of trainings × seeds on Ray Tune, resumable, then aggregated.

    python -m learn sweep --seeds 1 2 3 --robots 1 2 4 8 --preset quick --max-minutes 30 --out sweeps/exp1
    python -m learn sweep --file grid.toml --out sweeps/exp2 [--address auto]
    python -m learn sweep --aggregate sweeps/exp1

Rerunning a command finishes what it left: finished trials are skipped, unfinished ones resume from
their checkpoints. Exit status: 0 every trial finished, 1 some failed, 2 bad input, 130 interrupted.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from kiloforge.cliparse import ArgumentParser, error_line, program
from kiloforge.errors import InputError
from kiloforge.interrupts import exit_status
from kiloforge.validate import int_arg

from sim.config import DEFAULT_WORLD
from sim.config import PRESETS as WORLD_PRESETS

from ..config import PRESETS, ConfigError
from . import trial as tr
from .aggregate import aggregate, check_one_task, write_manifest
from .grid import Grid, Trial, build_grid, expand, read_grid_file

PROG = "python -m learn sweep"
INSTALL_HINT = "Ray Tune is not installed: pip install 'kiloforge[sweep]'"


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog=PROG, description="Train a grid of configurations × seeds on Ray Tune (local or a cluster), "
                                       "resumably, and aggregate the results over seeds.")
    g = p.add_argument_group("grid (command-line options replace the --file's)")
    g.add_argument("--file", default=None, help="grid file (.json or .toml; see docs/sweeps.md)")
    g.add_argument("--trainer", choices=tr.TRAINERS, default=None, help="trainer (default magddpg)")
    presets = "; ".join(f"{t}: {', '.join(PRESETS[t])}" for t in tr.TRAINERS)
    g.add_argument("--preset", nargs="+", default=None, help=f"training preset(s) (an axis when several): {presets}")
    g.add_argument("--seeds", nargs="+", type=int_arg(), default=None, help="seeds (default 1)")
    g.add_argument("--robots", nargs="+", type=int_arg(), default=None, help="robots trained together (n_robots)")
    g.add_argument("--world", nargs="+", default=None,
                   help=f"world preset(s): {', '.join(sorted(WORLD_PRESETS))} (default {DEFAULT_WORLD})")
    g.add_argument("--task", default=None,
                   help="the sweep's task (sim.tasks): a name or path/to/file.py:ClassName (default localisation); "
                        "with --aggregate, the task file of a sweep of a plug-in task")
    g.add_argument("--history", nargs="+", type=int_arg(), default=None, help="history lengths (t_prev; magddpg)")
    g.add_argument("--grid", nargs="+", action="extend", default=None, metavar="KEY=V1,V2",
                   help="any config field: comma-separated values, tuples as 32x32, or a JSON list")
    g.add_argument("--max-minutes", type=float, default=None,
                   help="wall-clock budget per trial over all its sessions (default: the preset's)")
    g.add_argument("--cpus-per-trial", type=float, default=None, help="CPUs per trial (default 1; torch threads)")
    g.add_argument("--eval-robots", nargs="+", type=int_arg(), default=None,
                   help="evaluate each trial's best policy and the baselines at these swarm sizes")
    g.add_argument("--eval-episodes", type=int_arg(), default=None, help="episodes of that evaluation (default 500)")
    g.add_argument("--eval-steps", type=int_arg(), default=None, help="steps per episode of that evaluation (default 500)")
    r = p.add_argument_group("where and how")
    r.add_argument("--out", default=None, help="sweep directory (one run directory per trial)")
    r.add_argument("--address", default=None,
                   help="an existing Ray cluster, HOST:PORT or auto (default: a private local Ray)")
    r.add_argument("--num-cpus", type=int_arg(), default=None, help="CPUs of the local Ray (default: all)")
    r.add_argument("--dry-run", action="store_true", help="list the trials and their state; run nothing")
    r.add_argument("--quiet", action="store_true", help="no progress")
    r.add_argument("--aggregate", metavar="DIR", default=None,
                   help="only aggregate the sweep directory DIR (summary.json, table, plots)")
    return p


def plan(args: argparse.Namespace) -> tuple[Grid, list[Trial], Path]:
    """The validated grid, its trials and the sweep directory (nothing is written)."""
    if not args.out:
        raise ConfigError("--out DIR is required (the sweep directory)")
    if args.address and args.num_cpus is not None:
        raise ConfigError("--num-cpus sizes the local Ray; a cluster given with --address has its own CPUs")
    if args.num_cpus is not None and args.num_cpus < 1:
        raise ConfigError(f"--num-cpus must be >= 1, got {args.num_cpus}")
    grid = build_grid(read_grid_file(args.file) if args.file else None, trainer=args.trainer, presets=args.preset,
                      seeds=args.seeds, robots=args.robots, world=args.world,
                      task=None if args.task is None else [args.task], history=args.history, grid=args.grid,
                      max_minutes=args.max_minutes, cpus_per_trial=args.cpus_per_trial,
                      eval_robots=args.eval_robots, eval_episodes=args.eval_episodes, eval_steps=args.eval_steps)
    trials = expand(grid)
    local_cpus = args.num_cpus or os.cpu_count() or 1
    if not args.address and grid.cpus_per_trial > local_cpus:
        raise ConfigError(f"--cpus-per-trial {grid.cpus_per_trial:g} is more than the {local_cpus} CPUs of the local Ray")
    sweep_dir = Path(args.out)
    if sweep_dir.exists() and not sweep_dir.is_dir():
        raise ConfigError(f"--out '{sweep_dir}' is not a directory")
    check_one_task(sweep_dir, trials)
    return grid, trials, sweep_dir


def states(grid: Grid, trials: list[Trial], sweep_dir: Path) -> dict[str, str]:
    """Trial name → new / resume / finished / evaluate; refuses run directories of other configurations."""
    out = {}
    for t in trials:
        cfg = tr.resolve_config(t.trainer, t.preset, t.overrides)
        run_dir = sweep_dir / t.name
        tr.check_compatible(t.trainer, cfg, run_dir)
        budget = cfg.max_minutes if grid.max_minutes is None else grid.max_minutes
        s = tr.trial_state(cfg, run_dir, budget)
        out[t.name] = "evaluate" if s == "finished" and not tr.evaluated(run_dir, grid.evaluation) else s
    return out


def main_sweep(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return _run(args)
    except (ConfigError, InputError) as e:
        print(error_line(program(PROG), e), file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # trials checkpoint as they train; the summary is written atomically
        print(error_line(program(PROG), "interrupted; finished trials and the others' checkpoints are kept "
                                        "(the same command resumes the sweep)"), file=sys.stderr)
        return exit_status(e)


def _run(args: argparse.Namespace) -> int:
    if args.aggregate:
        if not Path(args.aggregate).is_dir():
            raise ConfigError(f"'{args.aggregate}' is not a directory")
        aggregate(args.aggregate, task=args.task)
        print(f"wrote {Path(args.aggregate) / 'summary.json'}")
        return 0
    grid, trials, sweep_dir = plan(args)
    state = states(grid, trials, sweep_dir)
    pending = [t for t in trials if state[t.name] != "finished"]
    counts = {s: sum(v == s for v in state.values()) for s in ("finished", "resume", "new", "evaluate")}
    where = f"the Ray cluster at {args.address}" if args.address else "a local Ray"
    summary = (f"{len(trials)} trials in {sweep_dir}: {counts['finished']} finished, {counts['resume']} to resume, "
               f"{counts['new']} to start" + (f", {counts['evaluate']} to evaluate" if counts["evaluate"] else ""))
    if args.dry_run:
        print(summary)
        for t in trials:
            print(f"  {state[t.name]:9s} {t.name}")
        return 0
    if pending:
        try:
            from . import execute
        except ImportError as e:
            if (e.name or "").split(".")[0] != "ray":
                raise
            raise ConfigError(INSTALL_HINT) from None
    sweep_dir.mkdir(parents=True, exist_ok=True)
    write_manifest(sweep_dir, grid, trials)
    if not args.quiet:
        print(f"sweep: {summary}" + (f"; running on {where}" if pending else ""), flush=True)
    errors: dict[str, str] = {}
    if pending:
        outcome = execute.run_trials(sweep_dir, grid, trials, pending, done=counts["finished"],
                                     address=args.address, num_cpus=args.num_cpus, progress=not args.quiet)
        errors = outcome.errors
    aggregate(sweep_dir, log=(lambda _m: None) if args.quiet else print, task=tr.task_spec(t.config for t in trials))
    after = states(grid, trials, sweep_dir)
    left = [n for n, s in after.items() if s != "finished"]
    print(f"wrote {sweep_dir / 'summary.json'}, {sweep_dir / 'table.txt'}"
          + (f", {sweep_dir / 'learning_curves.png'}" if (sweep_dir / "learning_curves.png").exists() else ""))
    for name, err in errors.items():
        print(f"failed: {name}: {err}", file=sys.stderr)
    if errors:
        return 1
    if left:
        print(f"stopped with {len(left)} of {len(trials)} trials unfinished; rerun the same command to resume them",
              file=sys.stderr)
        return 130
    return 0
